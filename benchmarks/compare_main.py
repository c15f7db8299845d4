"""A benchmark script of this tree against the same script of another checkout, A/B interleaved.

Runs ``python benchmarks/SCRIPT ARGS`` of the baseline checkout (A, e.g. the main
branch) and of this tree (B) in turn, each with its own package first on
``PYTHONPATH``, and reads the figures each run prints: the claim lines of
:mod:`claims` (ratios measured inside the run, e.g. branch steps/s over the raw
processes' ceiling) and ``NAME: VALUE steps/s`` lines. It prints, per figure, the
median of A's runs, of B's, and the median (and range) of B / A over the pairs. On a
shared machine the load drifts: the runs alternate, and the pairs alternate which side
goes first (A B, B A, A B, ...), so that both sides meet the same load and a steady
drift favours neither. The ratios measured inside a run (to a ceiling timed in the same
run) cancel most of the load; absolute rates (``steps/s``) cancel it only over pairs.

Run (from this tree's root)::

    python benchmarks/compare_main.py --baseline /work/main --pairs 4 -- \\
        bench_ceiling.py --repeats 1 --engines whole lockstep
    python benchmarks/compare_main.py --baseline /work/main --pairs 4 -- \\
        bench_branching.py --repeats 2
    taskset -c 0 python benchmarks/compare_main.py --baseline /work/main --pairs 2 \\
        --same-script -- bench_tensor_env.py --sizes 1024 8192 --no-highway --peers-only \\
        --highjax-python /work/venv-jax/bin/python

A ratio B / A above 1 means this tree's figure is higher (for rates and ratios to a
ceiling: faster; for CPU ms per step: slower).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
# "  <name>   0.8466   (no goal) ..." or "... goal >=0.85  MET ...", as claims.claim prints.
CLAIM = re.compile(r"^  (?P<name>\S.*?)\s+(?P<value>-?\d+\.\d{4})\s{3}(?:goal|\(no goal\))")
# "       W=1:    41.2 steps/s   (range ...)", as bench_branching prints its rates.
RATE = re.compile(r"^\s+(?P<name>[^:]+):\s+(?P<value>-?\d+(?:\.\d+)?) steps/s")
# "       W=1:   1.52 /  22.31", bench_branching's CPU ms per branch step, parent / workers.
CPU = re.compile(r"^\s+(?P<name>W=[^:]+):\s+(?P<parent>[\d.]+) /\s+(?P<workers>[\d.]+)$")


def figures(text: str) -> dict[str, float]:
    """The figures of one run's output: claim values, rates and CPU per step, by name.

    CPU time per step (of the parent, of the workers) barely moves with the machine's
    load, where rates do: on a shared machine it is the steadier figure.

    Example:
        >>> figures("  W=1:    41.2 steps/s   (range 40-42)\\n"
        ...         "  merge-v0: ratio      0.8466   (no goal)     load 2\\n"
        ...         "       W=2:   1.50 /  22.00\\n")  # doctest: +NORMALIZE_WHITESPACE
        {'W=1 steps/s': 41.2, 'merge-v0: ratio': 0.8466,
         'W=2 parent CPU ms/step': 1.5, 'W=2 workers CPU ms/step': 22.0}
    """
    out: dict[str, float] = {}
    for line in text.splitlines():
        match = CLAIM.match(line)
        if match:
            out[match["name"]] = float(match["value"])
            continue
        match = RATE.match(line)
        if match:
            out[f"{match['name'].strip()} steps/s"] = float(match["value"])
            continue
        match = CPU.match(line)
        if match:
            out[f"{match['name'].strip()} parent CPU ms/step"] = float(match["parent"])
            out[f"{match['name'].strip()} workers CPU ms/step"] = float(match["workers"])
    return out


def run_once(
    tree: Path, script: str, args: list[str], script_tree: Path | None = None
) -> dict[str, float]:
    """Run ``script_tree``'s (default ``tree``'s) ``benchmarks/script``, ``tree`` on the path."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    env.pop("BENCH_CLAIMS", None)  # the comparison's runs are not the benchmarks page's
    proc = subprocess.run(
        [sys.executable, script, *args],
        cwd=(script_tree or tree) / "benchmarks",
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{script} failed in {tree}:\n{proc.stderr[-3000:]}")
    return figures(proc.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--baseline", type=Path, required=True, help="checkout A (e.g. main)")
    parser.add_argument("--pairs", type=int, default=4, help="A/B pairs: A B, B A, A B, ...")
    parser.add_argument(
        "--same-script",
        action="store_true",
        help="run this tree's script on both sides (only the package differs): for a "
        "script whose options the baseline's copy lacks",
    )
    parser.add_argument("script", help="a script of benchmarks/, e.g. bench_ceiling.py")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="the script's arguments")
    opts = parser.parse_args()
    sides = {"A": opts.baseline.resolve(), "B": HERE}
    runs: dict[str, list[dict[str, float]]] = {"A": [], "B": []}
    load = [os.getloadavg()[0]]
    for pair in range(opts.pairs):
        for side in ("A", "B") if pair % 2 == 0 else ("B", "A"):
            script_tree = HERE if opts.same_script else None
            runs[side].append(run_once(sides[side], opts.script, opts.args, script_tree))
            load.append(os.getloadavg()[0])
        print(f"pair {pair + 1}/{opts.pairs} done", file=sys.stderr, flush=True)
    names = [n for n in runs["A"][0] if all(n in r for r in runs["A"] + runs["B"])]
    print(
        f"{opts.script} {' '.join(opts.args)}: {opts.pairs} pairs run A B, B A, A B, ...; "
        f"A = {sides['A']}, B = {sides['B']}; {os.cpu_count()} cores, 1-minute load "
        f"{min(load):.1f}-{max(load):.1f}"
    )
    width = max([len(n) for n in names] + [6])
    print(f"  {'figure':<{width}} {'A median':>9} {'B median':>9} {'B/A median (range)':>22}")
    for name in names:
        a = [r[name] for r in runs["A"]]
        b = [r[name] for r in runs["B"]]
        ratios = [y / x for x, y in zip(a, b, strict=True) if x]
        cell = (
            f"{statistics.median(ratios):.3f} ({min(ratios):.2f}-{max(ratios):.2f})"
            if ratios
            else "n/a"
        )
        print(
            f"  {name:<{width}} {statistics.median(a):9.4g} {statistics.median(b):9.4g} {cell:>22}"
        )


if __name__ == "__main__":
    main()
