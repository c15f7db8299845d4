"""The docstring examples of the library run as tests, and every public name has one.

The public API (the floors' ``__all__``) also stays within its budget of names.

Each module's examples run in this process with the standard library's ``doctest``
(like ``pytest --doctest-modules torchrl_grpo``, with ELLIPSIS and
NORMALIZE_WHITESPACE). Examples that need Ray are marked ``# doctest: +SKIP``;
without Ray installed, a module whose import or examples fail only for lack of
Ray is skipped instead of failed.
"""

from __future__ import annotations

import doctest
import importlib
import importlib.util
import inspect
import multiprocessing
import pkgutil
import typing
from types import ModuleType

import pytest
import torch

import torchrl_grpo
from torchrl_grpo.envs.highway import schema

OPTIONFLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE

# The subpackages whose ``__all__`` is the public API.
SUBPACKAGES = ("sim", "envs", "branching", "objectives", "modules", "training", "distributed")

# Public names that are not classes or functions: constants and ``Literal`` type
# aliases have no docstring of their own (``STATE_KEY.__doc__`` is ``str``'s), so
# they are documented in their module and checked to be plain data only. Anything
# else in an ``__all__`` (a class, a function, or an unexpected callable) must have
# an example. No public class or function is excluded.
DATA_TYPES = (str, int, float, bool, tuple, frozenset, dict, list)

HAS_RAY = importlib.util.find_spec("ray") is not None

# The snapshot schema's process-global registries, which register_vehicle_class and
# register_class_parameter (and so their examples) extend.
_SCHEMA_REGISTRY = (
    schema.FIELDS,
    schema.VEHICLE_CLASSES,
    schema.CLASS_PARAMETERS,
    schema.PRISTINE_CLASS_PARAMETERS,
)


def _walk_error(name: str) -> None:
    # Called inside pkgutil's ``except`` block: re-raise, a package that does not
    # import must not silently drop its modules from the test.
    raise


def library_modules() -> list[str]:
    """``torchrl_grpo`` and every module below it."""
    found = pkgutil.walk_packages(torchrl_grpo.__path__, "torchrl_grpo.", onerror=_walk_error)
    return ["torchrl_grpo", *sorted(info.name for info in found)]


def _is_missing_ray(exc: BaseException) -> bool:
    name = getattr(exc, "name", None) or ""
    return isinstance(exc, ImportError) and (name == "ray" or name.startswith("ray."))


class _Runner(doctest.DocTestRunner):
    """Keeps the exceptions that examples raised, to tell a missing Ray apart."""

    def __init__(self) -> None:
        super().__init__(verbose=False, optionflags=OPTIONFLAGS)
        self.exceptions: list[BaseException] = []

    def report_unexpected_exception(self, out, test, example, exc_info) -> None:
        self.exceptions.append(exc_info[1])
        super().report_unexpected_exception(out, test, example, exc_info)


def _import(name: str) -> ModuleType:
    try:
        return importlib.import_module(name)
    except ImportError as err:
        if _is_missing_ray(err) and not HAS_RAY:
            pytest.skip(f"{name} needs Ray, which is not installed")
        raise


@pytest.mark.parametrize("module_name", library_modules())
def test_docstring_examples_run(module_name):
    module = _import(module_name)
    tests = doctest.DocTestFinder(exclude_empty=True).find(module, module_name)
    runner = _Runner()
    report: list[str] = []
    # Examples seed torch or set its threads (a GroupWorker does), or register classes
    # in the snapshot schema (schema.py's own): leave no trace. A registration left in
    # this process would give its later snapshots a layout that fresh env workers lack.
    rng_state, num_threads = torch.get_rng_state(), torch.get_num_threads()
    registry = [(table, table.copy()) for table in _SCHEMA_REGISTRY]
    children = {p.pid for p in multiprocessing.active_children()}
    try:
        for test in sorted(tests, key=lambda t: t.name):
            runner.run(test, out=report.append)
    finally:
        torch.set_rng_state(rng_state)
        torch.set_num_threads(num_threads)
        for table, saved in registry:  # in place: the library holds these very objects
            table.clear()
            if isinstance(table, dict):
                table.update(saved)
            else:
                table.extend(saved)
    failed, attempted = runner.failures, runner.tries
    only_ray = len(runner.exceptions) == failed and all(map(_is_missing_ray, runner.exceptions))
    if failed and only_ray and not HAS_RAY:
        pytest.skip(f"the examples of {module_name} need Ray, which is not installed")
    assert not failed, f"{failed} of {attempted} examples of {module_name} failed:\n" + "".join(
        report
    )
    left = [p for p in multiprocessing.active_children() if p.pid not in children]
    for process in left:
        process.join(timeout=10)
    alive = [p for p in left if p.is_alive()]
    assert not alive, f"the examples of {module_name} left worker processes running: {alive}"


def _is_data(obj: object) -> bool:
    """A constant or a type alias (``Literal[...]``), which has no docstring of its own."""
    return isinstance(obj, DATA_TYPES) or typing.get_origin(obj) is typing.Literal


@pytest.mark.parametrize("subpackage", SUBPACKAGES)
def test_every_public_class_and_function_has_an_example(subpackage):
    package = importlib.import_module(f"torchrl_grpo.{subpackage}")
    missing, unclassified = [], []
    for name in package.__all__:
        obj = getattr(package, name)
        if inspect.isclass(obj) or inspect.isroutine(obj):
            # ``__doc__``, not ``inspect.getdoc``: a class must not borrow its base's example.
            if ">>>" not in (obj.__doc__ or ""):
                missing.append(name)
        elif not _is_data(obj):
            unclassified.append(f"{name} ({type(obj).__name__})")
    assert not missing, (
        f"public names of torchrl_grpo.{subpackage} without a '>>>' example in their "
        f"docstring: {missing}"
    )
    assert not unclassified, (
        f"public names of torchrl_grpo.{subpackage} that are neither a class, a function "
        f"nor plain data (give them an example and extend this test): {unclassified}"
    )


# The public API's budget (issue 40): what a user touches, not every name of the package.
MAX_PUBLIC_NAMES = 120


def test_the_public_api_stays_small_and_only_the_floors_export():
    counts = {
        sub: len(importlib.import_module(f"torchrl_grpo.{sub}").__all__) for sub in SUBPACKAGES
    }
    assert sum(counts.values()) <= MAX_PUBLIC_NAMES, counts
    # A nested package is implementation: its names are reached through the floor above it
    # or through their own modules, so it has no ``__all__`` of its own.
    nested = [
        info.name
        for info in pkgutil.walk_packages(torchrl_grpo.__path__, "torchrl_grpo.")
        if info.ispkg
        and info.name.count(".") > 1
        and info.name.split(".")[1] in SUBPACKAGES
        and hasattr(importlib.import_module(info.name), "__all__")
    ]
    assert not nested, f"nested packages with an __all__: {nested}"
