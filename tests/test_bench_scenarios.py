"""benchmarks/bench_scenarios.py keeps each run's episodes under a key of that run alone."""

import sys
from pathlib import Path

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
