"""The Python examples of the README and of docs/*.md run as written.

Each file's examples run in a fresh interpreter, in order, so that a registration in
one file (a custom vehicle class) cannot leak into other tests.
"""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


# The longest example files (20 s each, worker processes and Ray) run with -m slow, to keep
# the default suite within its 10-minute budget.
SLOW_DOCUMENTS = {"distributed.md", "envs.md", "branching.md", "sim.md"}


@pytest.mark.parametrize(
    "path",
    [
        pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW_DOCUMENTS else p
        for p in DOCUMENTS
        if python_blocks(p)
    ],
    ids=lambda p: p.name,
)
def test_examples_run(path, tmp_path):
    script = tmp_path / "examples.py"
    body = "\n\n".join(python_blocks(path))
    # A __main__ guard: ParallelEnv workers re-import the main module when they spawn.
    script.write_text(
        "def main():\n"
        + "\n".join("    " + line for line in body.splitlines())
        + "\n\n\nif __name__ == '__main__':\n    main()\n"
    )
    result = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert result.returncode == 0, f"{path.name} examples failed:\n{result.stderr[-3000:]}"


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    assert "# tests" in ci
    lines = [
        line for line in (ROOT / "README.md").read_text().splitlines() if line.endswith("# tests")
    ]
    assert len(lines) == 1 and "pytest" in lines[0]
