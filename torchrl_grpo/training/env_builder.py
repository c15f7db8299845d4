"""Builders of the ``env`` and ``rollout`` groups: evaluation envs and rollout workers."""

from __future__ import annotations

from typing import Any, Literal

from omegaconf import DictConfig, OmegaConf
from torchrl.envs import EnvBase

from torchrl_grpo.branching import Backend, make_branch_env
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import KinematicsLayout

__all__ = [
    "RolloutBackend",
    "env_overrides",
    "episode_step_limit",
    "make_env",
    "make_layout",
    "make_rollout_env",
]

#: How the rollout workers run (``rollout.backend``): a :data:`~torchrl_grpo.branching.Backend`
#: of :func:`~torchrl_grpo.branching.make_branch_env`, or ``"ray"`` (GRPO groups collected
#: on Ray actors, :class:`~torchrl_grpo.distributed.RayGroupCollector`).
RolloutBackend = Literal[Backend, "ray"]


def env_overrides(env_cfg: DictConfig) -> dict[str, Any]:
    """The highway-env config overrides of ``env.config`` as a plain dict.

    Example:
        >>> env_overrides(OmegaConf.create({"config": {"lanes_count": 4}}))
        {'lanes_count': 4}
    """
    config = env_cfg.get("config") or {}
    if isinstance(config, DictConfig):
        config = OmegaConf.to_container(config, resolve=True)
    return dict(config)


def make_env(
    env_cfg: DictConfig,
    *,
    seed: int | None = None,
    render_mode: str | None = None,
    return_state: bool = False,
) -> HighwayEnv:
    """One :class:`~torchrl_grpo.envs.HighwayEnv` in this process (evaluation, specs).

    Args:
        env_cfg: the ``env`` config group.
        seed: seed of the first episode.
        render_mode: ``"rgb_array"`` to record videos.
        return_state: write the state after every step into the output.

    Example:
        >>> cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}})
        >>> make_env(cfg, seed=0).action_spec.n
        5
    """
    return HighwayEnv(
        env_cfg.scenario,
        config=env_overrides(env_cfg),
        seed=seed,
        render_mode=render_mode,
        return_state=return_state,
    )


def make_rollout_env(
    env_cfg: DictConfig, rollout_cfg: DictConfig, *, snapshots: bool = True, **env_kwargs: Any
) -> EnvBase:
    """The W training workers (``rollout.num_workers``, ``rollout.backend``).

    GRPO branches read every worker's state through shared memory (``snapshots``);
    PPO's workers write their state after every step instead (``return_state=True``),
    which lets a checkpoint restore them mid-episode.

    Example:
        >>> env_cfg = OmegaConf.create({"scenario": "merge-v0", "config": {}})
        >>> rollout = OmegaConf.create({"num_workers": 1, "backend": "single",
        ...                             "mp_start_method": None})
        >>> make_rollout_env(env_cfg, rollout).batch_size
        torch.Size([])
    """
    return make_branch_env(
        env_cfg.scenario,
        int(rollout_cfg.num_workers),
        config=env_overrides(env_cfg),
        backend=str(rollout_cfg.backend),
        snapshots=snapshots,
        mp_start_method=rollout_cfg.get("mp_start_method"),
        **env_kwargs,
    )


def make_layout(env: HighwayEnv) -> KinematicsLayout | None:
    """The Kinematics layout scripted baselines read, or ``None`` for other observations.

    Example:
        >>> make_layout(HighwayEnv("highway-fast-v0", seed=0)).lanes_count
        3
    """
    obs_type = env.config.get("observation", {}).get("type")
    if obs_type != "Kinematics":
        return None
    return KinematicsLayout.from_highway_config(env.config)


def episode_step_limit(env: HighwayEnv, fallback: int) -> int:
    """The scenario's episode length in policy steps (``duration`` x ``policy_frequency``).

    Scenarios without a time limit (merge-v0 ends at the end of its road) give
    ``fallback``.

    Example:
        >>> episode_step_limit(HighwayEnv("highway-fast-v0", seed=0), 1000)
        30
    """
    duration = env.config.get("duration")
    if duration is None:
        return int(fallback)
    return int(round(float(duration) * float(env.config.get("policy_frequency", 1))))
