"""benchmarks/bench_gpu.py runs end to end on a CPU with tiny sizes (its CUDA parts skipped).

The script is meant for a GPU session of a few minutes: a failure found there costs the
session. Here every part runs once at toy sizes, and each figure must be a number.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_gpu  # noqa: E402


def test_bench_gpu_runs_on_cpu_with_tiny_sizes(tmp_path):
    out = bench_gpu.main(
        ["--device", "cpu", "--sizes", "16", "--seconds", "0.05", "--planner-worlds", "2",
         "--horizon", "1", "--train-frames", "64", "--budget", "120",
         "--json", str(tmp_path / "figures.json"),
         "--train-override", "experiment=smoke", "env.num_envs=16"]
    )  # fmt: skip
    assert out["device"] == "cpu"
    assert not any(k.startswith(("env-steps/s compiled", "env-steps/s graph")) for k in out)
    figures = {k: v for k, v in out.items() if k != "device"}
    failed = {k: v for k, v in figures.items() if not isinstance(v, int | float)}
    assert not failed, failed
    assert out["env-steps/s eager B=16"] > 0
    assert out["planner episodes finished"] == 2  # every driven world ends an episode
    assert out["training frames"] >= 64
    assert (tmp_path / "figures.json").exists()
