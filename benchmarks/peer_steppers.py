"""The peers' steppers that ``bench_tensor_env.py`` times beside TensorHighwayEnv.

Each returns a call that steps its simulator once (or, for HighJax, one timed block):
highway-env itself in this process, EnvPool's C++ port when ``envpool`` is installed,
and HighJax through ``highjax_worker.py`` under another Python (docs/benchmarks.md,
"Peers"). Every one drives always-IDLE and resets finished episodes.
"""

from __future__ import annotations

import atexit
import importlib.util
import subprocess
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv

#: The action every stepper drives: IDLE.
IDLE = 1


def highway_stepper(scenario: str = "highway-fast-v0", **kwargs) -> Callable[[], None]:
    """One step of highway-env, reset at the end of an episode."""
    env = HighwayEnv(scenario, seed=0, **kwargs)
    env.reset()
    action = TensorDict(action=torch.tensor(IDLE))

    def step() -> None:
        out = env.step(action.clone())
        if bool(out["next", "done"]):
            env.reset()

    return step


def envpool_stepper(
    batch: int, threads: int, scenario: str = "highway-fast-v0"
) -> Callable[[], None] | None:
    """One step of EnvPool's C++ port of the scenario with B envs, or None without envpool."""
    if importlib.util.find_spec("envpool") is None:
        return None
    import envpool
    import numpy as np

    env = envpool.make(
        scenario,
        env_type="gymnasium",
        num_envs=batch,
        batch_size=batch,
        num_threads=threads,
    )
    env.reset()
    action = np.full(batch, IDLE, dtype=np.int32)
    return lambda: env.step(action)  # EnvPool resets finished envs itself


def highjax_stepper(python: str, batch: int, threads: int) -> Callable[[], None]:
    """Blocks of HighJax steps run by ``highjax_worker.py`` under ``python``.

    The returned call steps one block; its rate is the worker's own timing (the pipe's
    round trip stays outside it), read back by :func:`rate` through ``last``.
    """
    worker = subprocess.Popen(
        [python, str(Path(__file__).with_name("highjax_worker.py")), "--batch", str(batch),
         "--threads", str(threads)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    if worker.stdout.readline().strip() != "ready":
        raise RuntimeError(f"highjax_worker.py under {python} did not start")
    atexit.register(worker.kill)
    calls = max(2, min(200, 20000 // batch))

    def block() -> float:
        worker.stdin.write(f"{calls}\n")
        worker.stdin.flush()
        return float(worker.stdout.readline())

    return block
