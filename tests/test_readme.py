"""The README's Python example runs as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_blocks_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "the README has no python example"
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, str(README), "exec"), namespace)  # noqa: S102
    assert "state" in namespace and "td0" in namespace
    assert namespace["td0"]["observation"].shape == namespace["td"]["observation"].shape[1:]


def test_ci_runs_the_readme_test_command():
    ci = (README.parent / ".ci" / "run").read_text()
    assert "# tests" in ci
    lines = [line for line in README.read_text().splitlines() if line.endswith("# tests")]
    assert len(lines) == 1 and "pytest" in lines[0]
