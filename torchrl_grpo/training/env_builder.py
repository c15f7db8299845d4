"""Builders of the ``env`` and ``rollout`` groups: evaluation envs and rollout workers."""

from __future__ import annotations

import logging
import os
from typing import Any, Literal

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import EnvBase

from torchrl_grpo.branching.branch_env import Backend, make_branch_env
from torchrl_grpo.envs.highway.step_modes import NATIVE_SCENARIOS, load_native
from torchrl_grpo.envs.highway.tensor_env import TensorHighwayEnv
from torchrl_grpo.envs.highway.tensor_params import check_tensor_config, tensor_params
from torchrl_grpo.envs.highway.wrapper import HighwayEnv
from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.sim.native_build import NativeBuildError

__all__ = [
    "steps_natively",
    "EnvBackend",
    "RolloutBackend",
    "check_device",
    "env_backend",
    "env_overrides",
    "episode_step_limit",
    "make_env",
    "make_layout",
    "make_rollout_env",
    "tensor_covers",
]

#: How the rollout workers run (``rollout.backend``): a
#: :data:`~torchrl_grpo.branching.branch_env.Backend` of
#: :func:`~torchrl_grpo.branching.make_branch_env`, or ``"ray"`` (GRPO groups collected on
#: Ray actors, :class:`~torchrl_grpo.distributed.RayGroupCollector`).
RolloutBackend = Literal[Backend, "ray"]
#: The simulator training runs on (``env.backend``): ``tensor`` (the batched simulator,
#: :class:`~torchrl_grpo.envs.TensorHighwayEnv`, its tensor step), ``native`` (the same
#: with its step in C++, ``native=True``: ``NATIVE_SCENARIOS`` on a CPU),
#: ``highway`` (highway-env itself, on ``rollout.backend`` workers), or ``auto``: the
#: tensor simulator where it covers the scenario and config (its C++ step where it has
#: one, on a CPU), highway-env elsewhere.
EnvBackend = Literal["auto", "tensor", "native", "highway"]

log = logging.getLogger(__name__)


def env_backend(env_cfg: DictConfig) -> Literal["tensor", "highway"]:
    """The simulator ``env.backend`` resolves to, logged (with the reason for ``auto``).

    Raises:
        ValueError: ``env.backend=tensor`` for a scenario or config the tensor simulator
            does not cover (its own message, naming the key).

    Example:
        >>> cfg = OmegaConf.create({"scenario": "racetrack-v0", "config": {}, "backend": "auto"})
        >>> env_backend(cfg)
        'highway'
        >>> env_backend(OmegaConf.merge(cfg, {"scenario": "highway-fast-v0"}))
        'tensor'
    """
    chosen = str(env_cfg.get("backend", "highway"))
    if chosen == "highway":
        return "highway"
    if chosen == "native" and env_cfg.scenario not in NATIVE_SCENARIOS:
        raise ValueError(
            f"env.backend=native steps {NATIVE_SCENARIOS} in C++, not {env_cfg.scenario!r}: "
            "use env.backend=tensor or auto"
        )
    try:
        check_tensor_config(env_cfg.scenario, env_overrides(env_cfg))
    except ValueError as err:
        if chosen in ("tensor", "native"):
            raise
        log.info("env.backend=auto: training on highway-env (%s)", err)
        return "highway"
    if chosen == "auto":
        log.info("env.backend=auto: training on the tensor simulator (%s)", env_cfg.scenario)
    return "tensor"


def steps_natively(env_cfg: DictConfig, device: str | torch.device = "cpu") -> bool:
    """Whether the tensor simulator steps in C++ (``TensorHighwayEnv(native=True)``).

    ``env.backend=native`` always; ``auto`` for ``NATIVE_SCENARIOS`` on a CPU, unless the
    C++ step cannot be built here (no compiler) or cannot hold the config (such as more
    than 16 target speeds): logged, and the tensor step then.
    Call it where :func:`env_backend` chose the tensor simulator.

    Example:
        >>> steps_natively(OmegaConf.create({"backend": "native"}))
        True
        >>> steps_natively(OmegaConf.create({"backend": "tensor", "scenario": "highway-v0"}))
        False
    """
    chosen = str(env_cfg.get("backend", "auto"))
    if chosen != "auto":
        return chosen == "native"
    if env_cfg.scenario not in NATIVE_SCENARIOS or torch.device(device).type != "cpu":
        return False
    try:
        load_native(env_cfg.scenario, tensor_params(env_cfg.scenario, env_overrides(env_cfg)))
    except NativeBuildError as err:
        log.warning("env.backend=auto: the tensor step, as the C++ one is unavailable (%s)", err)
        return False
    except ValueError as err:
        log.info(
            "env.backend=auto: the tensor step, as the C++ one cannot hold this config (%s)", err
        )
        return False
    return True


def tensor_covers(env_cfg: DictConfig) -> bool:
    """Whether the tensor simulator covers ``env_cfg``'s scenario and config.

    Example:
        >>> tensor_covers(OmegaConf.create({"scenario": "racetrack-v0", "config": {}}))
        False
        >>> tensor_covers(OmegaConf.create({"scenario": "merge-v0", "config": {}}))
        True
    """
    try:
        check_tensor_config(env_cfg.scenario, env_overrides(env_cfg))
    except ValueError:
        return False
    return True


def check_device(device: str) -> torch.device:
    """``device`` as a torch device; a clear error for a CUDA device that is not there.

    Example:
        >>> check_device("cpu")
        device(type='cpu')
    """
    try:
        found = torch.device(device)
    except RuntimeError as err:
        raise ValueError(f"device={device!r} is not a torch device: {err}") from None
    if found.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={device!r} was asked for, but torch finds no CUDA device")
    return found


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
    if render_mode == "rgb_array":
        # Frames are drawn off screen: SDL needs no display and no sound. Left to
        # probe them, it prints "XDG_RUNTIME_DIR is invalid" at every evaluation.
        os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    return HighwayEnv(
        env_cfg.scenario,
        config=env_overrides(env_cfg),
        seed=seed,
        render_mode=render_mode,
        return_state=return_state,
    )


def make_rollout_env(
    env_cfg: DictConfig,
    rollout_cfg: DictConfig,
    *,
    snapshots: bool = True,
    device: str = "cpu",
    seed: int | None = None,
    **env_kwargs: Any,
) -> EnvBase:
    """The env training collects from.

    On the tensor simulator (:func:`env_backend`): one
    :class:`~torchrl_grpo.envs.TensorHighwayEnv` of ``env.num_envs`` worlds on
    ``device``, whose rows are the branches (and trunks) of a batch. On highway-env: the
    W workers of ``rollout.num_workers`` and ``rollout.backend``; GRPO branches read every
    worker's state through shared memory (``snapshots``); PPO's workers write their state
    after every step instead (``return_state=True``), which lets a checkpoint restore
    them mid-episode.

    Example:
        >>> env_cfg = OmegaConf.create({"scenario": "merge-v0", "config": {}})
        >>> rollout = OmegaConf.create({"num_workers": 1, "backend": "single",
        ...                             "mp_start_method": None})
        >>> make_rollout_env(env_cfg, rollout).batch_size
        torch.Size([])
    """
    if env_backend(env_cfg) == "tensor":
        native = steps_natively(env_cfg, device)
        if native and str(env_cfg.get("backend")) == "auto":
            log.info("env.backend=auto: its C++ step (env.backend=tensor: the tensor step)")
        return TensorHighwayEnv(
            env_cfg.scenario,
            env_overrides(env_cfg),
            num_envs=int(env_cfg.num_envs),
            device=check_device(device),
            seed=seed,
            return_state=bool(env_kwargs.get("return_state", snapshots)),
            native=native,
        )
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
