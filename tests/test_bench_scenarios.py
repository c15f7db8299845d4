"""benchmarks/bench_scenarios.py: results keyed by run alone, and the --crash-margin flag."""

import argparse
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_scenarios  # noqa: E402


def _run(folder: Path, weights: bytes) -> Path:
    folder.mkdir(parents=True)
    (folder / "last.pt").write_bytes(weights)
    return folder


def test_runs_of_one_folder_name_elsewhere_keep_their_own_results(tmp_path):
    # A rerun at more frames, or a copy with another margin, in a folder of the same name.
    first = _run(tmp_path / "a" / "grpo_s0", b"weights of the 1.2M-frame run")
    second = _run(tmp_path / "b" / "grpo_s0", b"weights of the 2.4M-frame run")
    copy = _run(tmp_path / "c" / "grpo_s0", b"weights of the 1.2M-frame run")
    assert bench_scenarios.run_key(first) != bench_scenarios.run_key(second)
    assert bench_scenarios.run_key(first) == bench_scenarios.run_key(copy)
    assert bench_scenarios.run_key(first).startswith("grpo_s0_")


def test_crash_margin_flag_takes_a_probability_or_none():
    assert bench_scenarios.parse_margin("none") is None
    assert bench_scenarios.parse_margin("0.01") == 0.01
    for bad in ("2", "-0.1", "nan", "tight"):
        with pytest.raises(argparse.ArgumentTypeError, match=f"got '{bad}'"):
            bench_scenarios.parse_margin(bad)
