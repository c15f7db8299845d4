"""benchmarks/bench_gpu.py runs end to end on a CPU with tiny sizes (its CUDA parts skipped).

The script is meant for a GPU session of a few minutes: a failure found there costs the
session. Here every part runs once at toy sizes, and each figure must be a number.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_gpu  # noqa: E402
import torch  # noqa: E402

from torchrl_grpo.envs import TensorHighwayEnv  # noqa: E402
from torchrl_grpo.sim.reset import reset_world  # noqa: E402
from torchrl_grpo.sim.simulate import step, substep  # noqa: E402


def test_bench_gpu_runs_on_cpu_with_tiny_sizes(tmp_path):
    out = bench_gpu.main(
        ["--device", "cpu", "--sizes", "16", "--seconds", "0.05", "--planner-worlds", "2",
         "--horizon", "1", "--train-frames", "150", "--milestone-frames", "32",
         "--checkpoints", str(tmp_path / "ckpt"), "--budget", "120",
         "--json", str(tmp_path / "figures.json"),
         "--train-override", "experiment=smoke", "env.num_envs=16"]
    )  # fmt: skip
    assert out["device"] == "cpu"
    assert not any(k.startswith(("env-steps/s compiled", "env-steps/s graph")) for k in out)
    figures = {k: v for k, v in out.items() if k != "device"}
    failed = {k: v for k, v in figures.items() if not isinstance(v, int | float | list)}
    assert not failed, failed
    assert out["env-steps/s eager B=16"] > 0
    assert out["planner episodes finished"] == 2  # every driven world ends an episode
    assert out["training frames"] >= 150
    # A milestone at every 32 frames (a smoke iteration is 68) and at the end, each with
    # the policy saved then.
    curve = out["training milestones [frames, seconds]"]
    assert len(curve) == 3 and curve[-1][0] == out["training frames"]
    saved = sorted(p.name for p in (tmp_path / "ckpt").iterdir())
    assert saved == sorted(f"recipe_{frames}.pt" for frames, _ in curve)
    assert (tmp_path / "figures.json").exists()


def test_the_pure_step_of_the_compiled_kinds_is_the_step_plus_the_reset():
    # Eager here; on a GPU its parts are compiled (and captured in a CUDA graph).
    env = TensorHighwayEnv(num_envs=64, seed=4, dtype=torch.float64)
    action = torch.randint(0, 5, (64,), generator=torch.Generator().manual_seed(0))
    advance = bench_gpu.advance_fn(substep, bench_gpu._finish, action, env.params)
    ours = theirs = env._world
    resets = 0
    for _ in range(40):  # episodes of 30 steps at most: every world resets at least once
        ours = advance(ours)
        theirs, out = step(theirs, action, env.params)
        done = out["terminated"] | out["truncated"]
        resets += int(done.sum())
        theirs = reset_world(theirs, done, env.params)
    assert resets >= 64
    for a, b in zip(bench_gpu.tensors(ours), bench_gpu.tensors(theirs), strict=True):
        assert torch.equal(a, b)
