"""Shared by the lab's tests: the scripts of benchmarks/lab import each other by name.

They are scripts, not a package, so their folder goes on ``sys.path`` once here, before
pytest imports the test modules of this folder.
"""

import sys
from pathlib import Path

LAB = Path(__file__).resolve().parents[2] / "benchmarks" / "lab"
if str(LAB) not in sys.path:
    sys.path.insert(0, str(LAB))
