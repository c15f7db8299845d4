"""Puts ``benchmarks/`` on ``sys.path``: the lab scripts share its helpers (``claims``, ...).

Each lab script imports this module first, so that ``python benchmarks/lab/<script>.py``
finds ``claims`` and ``bench_crash_rates`` as the scripts of ``benchmarks/`` do.
"""

import sys
from pathlib import Path

_BENCHMARKS = str(Path(__file__).resolve().parents[1])
if _BENCHMARKS not in sys.path:
    sys.path.insert(1, _BENCHMARKS)
