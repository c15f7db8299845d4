"""The claims helper every benchmark prints through, and the page run_all writes."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import claims  # noqa: E402
import run_all  # noqa: E402


@pytest.mark.parametrize(
    ("value", "goal", "met"),
    [
        (0.97, ">=0.97", True),
        (0.9699, ">=0.97", False),
        (0.7, "<= 0.7", True),
        (0.71, "<=0.7", False),
        (0.0099, "<=1/100", True),
        (0.0101, "<=1/100", False),
        (1.7, ">1.7", False),
        (1.0, "<2", True),
    ],
)
def test_goal_met(value, goal, met):
    assert claims.goal_met(value, goal) is met


def test_a_goal_without_a_comparison_is_refused():
    with pytest.raises(ValueError, match="goal"):
        claims.goal_met(1.0, "0.97")


def test_claims_are_printed_and_recorded(tmp_path, monkeypatch, capsys):
    sink = tmp_path / "claims.jsonl"
    monkeypatch.setenv("BENCH_CLAIMS", str(sink))
    assert claims.claim("a / b", 0.5, "<=0.7") is True
    assert claims.claim("c / d", 2.0) is None
    out = capsys.readouterr().out
    assert "a / b" in out and "MET" in out and "NOT MET" not in out
    records = [json.loads(line) for line in sink.read_text().splitlines()]
    assert [(r["claim"], r["value"], r["goal"], r["met"]) for r in records] == [
        ("a / b", 0.5, "<=0.7", True),
        ("c / d", 2.0, None, None),
    ]


def test_page_counts_goals_and_shows_failures():
    rows = [
        {"claim": "x", "value": 0.5, "goal": "<=0.7", "met": True, "note": "", "command": "c1"},
        {"claim": "y", "value": 0.9, "goal": "<=0.7", "met": False, "note": "n", "command": "c1"},
        {"claim": "z", "value": 3.0, "goal": None, "met": None, "note": "", "command": "c2"},
    ]
    runs = [
        {"command": "c1", "what": "w", "exit": 0, "seconds": 1.0, "tail": ""},
        {"command": "c2", "what": "w", "exit": 1, "seconds": 1.0, "tail": "Traceback boom"},
    ]
    text = run_all.page(rows, runs, "today")
    assert "**1 of 2" in text
    assert "| y | 0.9 (n) | <=0.7 | **no** | `c1` |" in text
    assert "| z | 3 |  | (information) | `c2` |" in text
    assert "`c2` failed" in text and "Traceback boom" in text
