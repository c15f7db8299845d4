"""One line per measured claim, printed the same way by every benchmark script.

A claim is a ratio (or a count) measured in one run, with the goal it is held to.
``claim(...)`` prints it; when the ``BENCH_CLAIMS`` environment variable names a file
(``run_all.py`` sets it), the claim is also appended to that file as a JSON line, so
the benchmarks page is built from what the scripts measured, not from their text.
"""

from __future__ import annotations

import json
import operator
import os
import sys
from pathlib import Path

_OPS = {">=": operator.ge, "<=": operator.le, ">": operator.gt, "<": operator.lt}


def goal_met(value: float, goal: str) -> bool:
    """Whether ``value`` meets ``goal``, written as ``">=0.97"``, ``"<= 0.7"`` or ``"<1/100"``."""
    text = goal.replace(" ", "")
    for symbol in (">=", "<=", ">", "<"):
        if text.startswith(symbol):
            bound = text[len(symbol) :]
            num, _, den = bound.partition("/")
            limit = float(num) / float(den) if den else float(num)
            return _OPS[symbol](value, limit)
    raise ValueError(f"a goal is '>=x', '<=x', '>x' or '<x', got {goal!r}")


def claim(name: str, value: float, goal: str | None = None, *, note: str = "") -> bool | None:
    """Print one claim (and record it under ``$BENCH_CLAIMS``); return whether it is met.

    Args:
        name: what is measured, e.g. ``"merge-v0: HighwayEnv / raw step throughput"``.
        value: the measured ratio.
        goal: e.g. ``">=0.97"``; ``None`` for a figure printed for information.
        note: a short qualifier shown beside the value (the conditions of the run).
    """
    met = None if goal is None else goal_met(value, goal)
    verdict = "" if met is None else ("MET" if met else "NOT MET")
    goal_text = f"goal {goal:<7}" if goal else "(no goal)   "
    print(f"  {name:<60} {value:10.4f}   {goal_text} {verdict}{'  ' + note if note else ''}")
    sink = os.environ.get("BENCH_CLAIMS")
    if sink:
        record = {
            "script": Path(sys.argv[0]).name,
            "claim": name,
            "value": value,
            "goal": goal,
            "met": met,
            "note": note,
        }
        with open(sink, "a") as f:
            f.write(json.dumps(record) + "\n")
    return met
