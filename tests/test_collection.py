"""The test folders collect together in one pytest call, in any order (#44).

The test folders are not packages: pytest puts each folder on ``sys.path`` and imports its
modules by their bare names. Two folders' modules of one name, or a test importing
``conftest`` by name, then resolve to whichever folder was imported last.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

TESTS = Path(__file__).resolve().parent
# pytest imports each conftest.py under a name of its own, so these may repeat.
PYTEST_OWN = {"conftest.py", "__init__.py"}


def test_no_two_test_folders_hold_a_module_of_one_name():
    folders = defaultdict(list)
    for path in TESTS.rglob("*.py"):
        if path.name not in PYTEST_OWN:
            folders[path.name].append(str(path.parent.relative_to(TESTS)))
    assert {name: dirs for name, dirs in folders.items() if len(dirs) > 1} == {}


def test_no_test_module_imports_conftest_by_name():
    importers = []
    for path in TESTS.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            if any(name.split(".")[0] == "conftest" for name in names):
                importers.append(str(path.relative_to(TESTS)))
    assert importers == []


def test_training_and_objectives_collect_in_one_call():
    # The order that failed: objectives' conftest imported last, then training's tests.
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-n0", "-p", "no:cacheprovider"]
        + [str(TESTS / "training"), str(TESTS / "objectives")],
        cwd=TESTS.parent,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "error" not in proc.stdout.splitlines()[-1].lower()
