"""``rollout=ray``: the recipe's GRPO groups collected by Ray actors.

Each actor builds its own env: a shard of the tensor simulator where it covers the
scenario (``env.backend``), else ``rollout.num_workers`` highway-env workers. The
learner's policy goes to every actor with the root source, so that actors run the
recipe's scripted tails and live trunks as a local collector does.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_grpo.branching.branch_env import make_branch_env
from torchrl_grpo.distributed.ray_collector import RayGroupCollector
from torchrl_grpo.envs.highway.tensor_env import TensorHighwayEnv
from torchrl_grpo.training.env_builder import (
    check_device,
    env_backend,
    env_overrides,
    steps_natively,
)

__all__ = ["actor_env", "make_ray_collector"]


def actor_env(cfg: DictConfig) -> tuple[Callable[[], EnvBase], dict[str, Any]]:
    """The env factory every Ray actor calls, and what each actor reserves for it.

    On the tensor simulator an actor steps ``ceil(env.num_envs / num_actors)`` worlds on
    ``cfg.device``, one GPU per actor when that is ``cuda``; one actor therefore
    collects exactly as the local run does. On highway-env it runs
    ``rollout.num_workers`` workers with ``rollout.backend``, with 1 GiB of memory plus
    400 MiB per worker process.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"device": "cpu", "env": {"scenario": "highway-fast-v0",
        ...     "config": {}, "backend": "auto", "num_envs": 1280},
        ...     "rollout": {"num_workers": 1, "backend": "single", "ray": {"num_actors": 2}}})
        >>> factory, options = actor_env(cfg)
        >>> env = factory()
        >>> type(env).__name__, env.batch_size, options
        ('TensorHighwayEnv', torch.Size([640]), {'memory': 1073741824})
    """
    rollout = cfg.rollout
    if env_backend(cfg.env) == "tensor":
        device = check_device(str(cfg.get("device", "cpu")))
        num_envs = math.ceil(int(cfg.env.num_envs) / int(rollout.ray.num_actors))
        factory = functools.partial(
            TensorHighwayEnv,
            str(cfg.env.scenario),
            env_overrides(cfg.env),
            num_envs=num_envs,
            device=str(device),
            return_state=True,
            native=steps_natively(cfg.env, device),
        )
        options: dict[str, Any] = {"memory": 1024**3}
        if device.type == "cuda":
            options["num_gpus"] = 1
        return factory, options
    backend = str(rollout.get("backend", "single"))
    factory = functools.partial(
        make_branch_env,
        str(cfg.env.scenario),
        int(rollout.get("num_workers", 1)),
        config=env_overrides(cfg.env),
        backend=backend,
        snapshots=True,
        mp_start_method=rollout.get("mp_start_method"),
    )
    # 1 GiB for the actor and its in-process env, 400 MiB more per worker process.
    workers = int(rollout.get("num_workers", 1)) if backend == "parallel" else 0
    return factory, {"memory": (1024 + 400 * workers) * 1024**2}


def make_ray_collector(
    cfg: DictConfig, policy: TensorDictModuleBase, roots: Any, seed: int
) -> RayGroupCollector:
    """The GRPO collector on Ray actors (``rollout=ray``, settings in ``rollout.ray``).

    Each actor builds the env of :func:`actor_env`. Ray is started on this machine (its
    cores, a 512 MiB object store) unless ``rollout.ray.address`` names a cluster
    (``auto``) or Ray already runs.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"algo": {"group_size": 2, "select": "best"},
        ...     "env": {"scenario": "merge-v0", "config": {}},
        ...     "rollout": {"horizon": 2, "groups_per_batch": 2, "decision_interval": 2,
        ...     "num_workers": 1, "backend": "single", "ray": {"num_actors": 2,
        ...     "num_cpus_per_actor": 0.5, "num_cpus": 2}}})
        >>> collector = make_ray_collector(cfg, None, "reset", seed=0)  # doctest: +SKIP
    """
    algo, rollout = cfg.algo, cfg.rollout
    ray_cfg = rollout.ray
    env_factory, options = actor_env(cfg)
    object_store_mb = ray_cfg.get("object_store_mb", 512)
    return RayGroupCollector(
        env_factory,
        policy,
        num_actors=int(ray_cfg.num_actors),
        group_size=int(algo.group_size),
        horizon=int(rollout.horizon),
        groups_per_batch=int(rollout.groups_per_batch),
        total_frames=-1,
        roots=roots,
        decision_interval=int(rollout.decision_interval),
        select=str(algo.select),
        seed=seed,
        num_cpus_per_actor=float(ray_cfg.get("num_cpus_per_actor", 1.0)),
        memory_per_actor=options["memory"],
        actor_options={"num_gpus": options["num_gpus"]} if "num_gpus" in options else None,
        max_restarts=int(ray_cfg.get("max_restarts", 3)),
        ray_init={
            "address": ray_cfg.get("address"),
            "num_cpus": ray_cfg.get("num_cpus"),
            "object_store_memory": None if object_store_mb is None else object_store_mb * 1024**2,
        },
    )
