"""The training tests' shared setup: the config root, tiny budgets, composition, scripts.

A plain module rather than conftest.py: another test folder's ``conftest`` would win the name
``conftest`` in ``sys.modules`` when both folders run in one pytest call.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from omegaconf import DictConfig
from tensordict import TensorDict

from torchrl_grpo.experimental.grpo_lab import GRPOLabConfig
from torchrl_grpo.training import compose_config as library_compose

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"

# The settings the recipes fix are keys of the experimental algo=grpo_lab (model=lab).
LAB_RUN = ["algo=grpo_lab", "model=lab"]


def LAB(**kwargs) -> GRPOLabConfig:  # noqa: N802  (reads as the schema it builds)
    """The lab's algo schema with ``kwargs`` set."""
    return GRPOLabConfig(name="grpo_lab", **kwargs)


# Budgets small enough for CI: one in-process env, a tiny network, no media.
TINY = [
    "experiment=smoke",
    "logger=none",
    "experiment.eval_every=0",
    "experiment.final_eval_episodes=0",
]


def compose_config(
    overrides: list[str], config_name: str = "config", conf: Path = CONF
) -> DictConfig:
    """Compose ``conf/<config_name>.yaml`` as the scripts do (a resume on its checkpoint's)."""
    return library_compose(overrides, config_name=config_name, conf_dir=conf)


def visited_states(n: int, seed: int = 7) -> TensorDict:
    """Observations of ``n`` fresh tensor worlds over 5 random steps: states to label."""
    from torchrl_grpo.envs import TensorHighwayEnv

    env = TensorHighwayEnv("highway-fast-v0", num_envs=n, seed=seed)
    return env.rollout(5, break_when_any_done=False).reshape(-1).select("observation")


def run_script(
    script: str, args: list[str], timeout: float = 120, cwd: Path = ROOT, **kwargs
) -> subprocess.CompletedProcess:
    """Run ``scripts/<script>`` in a subprocess, wandb offline, from ``cwd`` (the repository root).

    Hydra's relative folders (``outputs/``, a relative ``experiment.out_dir``) land in ``cwd``.
    """
    env = {**os.environ, "WANDB_MODE": "offline", "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / script), *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        **kwargs,
    )
