"""The package's floors: imports only go down, and no module imports itself back.

The floors are defined here, once, and drawn in docs/architecture.md. A module may
import from its own subpackage and from subpackages on lower floors; a cycle among
modules (lazy imports inside functions included) is refused as well.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchrl_grpo"

#: Subpackage -> floor. Ground floor: the simulator and the building blocks of learning.
FLOORS = {
    "sim": 0,
    "modules": 0,
    "objectives": 0,
    "envs": 1,
    "branching": 2,
    "distributed": 3,
    "training": 4,
    # The research variants, beside the library: they build on it, nothing imports them.
    "experimental": 5,
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in PACKAGE.rglob("*.py")}


def imports(path: Path, known: set[str]) -> set[str]:
    """The package's modules ``path`` imports (``from a import b``: ``a.b`` when it is a module)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.split(".")[0] != "torchrl_grpo":
                continue
            for alias in node.names:
                child = f"{node.module}.{alias.name}"
                out.add(child if child in known else node.module)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == "torchrl_grpo"}
    return out


def graph() -> dict[str, set[str]]:
    found = modules()
    known = set(found)
    return {name: imports(path, known) & known for name, path in found.items()}


def subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_subpackage_has_a_floor():
    subpackages = {subpackage(m) for m in modules()} - {None}
    assert subpackages == set(FLOORS), "give every subpackage a floor in FLOORS"


def test_imports_only_go_down():
    upward = []
    for source, targets in graph().items():
        here = subpackage(source)
        for target in targets:
            there = subpackage(target)
            if here is None or there is None or here == there:
                continue
            if FLOORS[there] >= FLOORS[here]:
                upward.append(f"{source} -> {target}")
    assert not upward, "imports that do not go down a floor:\n" + "\n".join(sorted(upward))


def test_no_import_cycle():
    edges = graph()
    cycles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt)
        path.pop()
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node)
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_the_simulator_imports_only_torch_and_tensordict():
    allowed = {"torch", "tensordict", "torchrl_grpo", "__future__"}
    stdlib = set(sys.stdlib_module_names)  # the C++ step's build uses ctypes, subprocess...
    strays = []
    for path in (PACKAGE / "sim").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for name in names:
                root = name.split(".")[0]
                if root not in allowed | stdlib or (
                    root == "torchrl_grpo" and not name.startswith("torchrl_grpo.sim")
                ):
                    strays.append(f"{path.name}: {name}")
    assert not strays, strays


def test_the_checker_sees_an_upward_import(tmp_path):
    # The same scan on a made-up pair of modules: envs importing training is refused.
    a = tmp_path / "a.py"
    a.write_text("from torchrl_grpo.training import Trainer\n")
    found = imports(a, {"torchrl_grpo.training"})
    assert found == {"torchrl_grpo.training"} and FLOORS["training"] > FLOORS["envs"]


def test_no_module_basename_names_two_things():
    # A file's name says what it holds: the same name in two subpackages would hold two
    # different things under one name (``codec.py`` once named three).
    seen: dict[str, list[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        if path.name != "__init__.py":
            seen.setdefault(path.name, []).append(str(path.relative_to(PACKAGE)))
    repeated = {name: paths for name, paths in seen.items() if len(paths) > 1}
    assert not repeated, repeated


#: What moved out of the core into ``torchrl_grpo.experimental`` (issue #40): the name,
#: the experimental module that defines it. No core module may define, import or name it.
MOVED_TO_EXPERIMENTAL = {
    "PriorLogits": "torchrl_grpo.experimental.prior",
    "PriorName": "torchrl_grpo.experimental.prior",
    "GroupDistillLoss": "torchrl_grpo.experimental.group_distill",
    "group_softmax_target": "torchrl_grpo.experimental.group_distill",
    "group_spread": "torchrl_grpo.experimental.group_distill",
    "GroupFitLossName": "torchrl_grpo.experimental.group_distill",
    "GroupFitWeightingName": "torchrl_grpo.experimental.group_distill",
    "lagging_copy": "torchrl_grpo.experimental.lagging_tail",
    "check_tail_sync": "torchrl_grpo.experimental.lagging_tail",
    "TrunkPolicyName": "torchrl_grpo.experimental.trunk_clock",
    "check_trunk_bounds": "torchrl_grpo.experimental.trunk_clock",
    "NeighbourFeatures": "torchrl_grpo.experimental.neighbour_features",
    "NeighbourMLP": "torchrl_grpo.experimental.neighbour_features",
    "NeighboursKind": "torchrl_grpo.experimental.neighbour_features",
    "build_neighbours": "torchrl_grpo.experimental.neighbour_features",
}


def _defined_names(path: Path) -> set[str]:
    out = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.ClassDef, ast.FunctionDef)):
            out.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            out |= {t.id for t in targets if isinstance(t, ast.Name)}
    return out


def test_the_moved_variants_live_in_experimental_only():
    found = modules()
    # Each core module's names, parsed once: used, imported and defined.
    core_names = {}
    for source, path in found.items():
        if subpackage(source) == "experimental":
            continue
        tree = ast.parse(path.read_text())
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        imported = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        names |= {alias.name for node in imported for alias in node.names}
        core_names[source] = names | _defined_names(path)
    strays = []
    for name, module in MOVED_TO_EXPERIMENTAL.items():
        assert name in _defined_names(found[module]), f"{module} defines {name}"
        strays += [f"{source}: {name}" for source, names in core_names.items() if name in names]
    assert not strays, "moved to experimental, still in the core:\n" + "\n".join(strays)


def test_the_core_never_imports_experimental():
    # Stated on its own, though test_imports_only_go_down implies it: a lazy import of a
    # research variant from the core is the cross-cutting branch issue #40 took out.
    edges = graph()
    strays = [
        f"{source} -> {target}"
        for source, targets in edges.items()
        if subpackage(source) != "experimental"
        for target in targets
        if subpackage(target) == "experimental"
    ]
    assert not strays, strays


#: The folders of code, and the most lines a file of code there may hold.
CODE_FOLDERS = ("torchrl_grpo", "benchmarks", "scripts", "tests", "tutorials", "docs/_ext")
MAX_LINES = 400


def test_no_code_file_is_over_400_lines():
    root = PACKAGE.parent
    long = {
        str(path.relative_to(root)): lines
        for folder in CODE_FOLDERS
        for path in (root / folder).rglob("*")
        if path.suffix in (".py", ".cpp", ".h")
        and (lines := len(path.read_text().splitlines())) > MAX_LINES
    }
    assert not long, f"files over {MAX_LINES} lines (split them by job): {long}"
