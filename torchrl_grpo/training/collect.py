"""Builder of the collectors: ``GroupCollector`` for GRPO, TorchRL's ``Collector`` for PPO.

Also saves and restores a collector's exact position for checkpoints:

- GRPO: the collector's counters plus its root source's seed chain and pending
  roots (trunk decision points not branched from yet).
- PPO: the collector's counters, its carrier (the current observation of every
  worker) and every worker's simulator state, read from the carrier: PPO workers
  write their state after each step (``return_state=True``), so a resumed run
  continues the same episodes, mid-episode.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import BaseCollector, Collector
from torchrl.envs import EnvBase

from torchrl_grpo.branching import STATE, GroupCollector

__all__ = ["collector_state", "env_frames", "load_collector_state", "make_collector"]

# Root-source attributes that the branching package's state_dict() does not cover yet
# (seed chain, pending trunk roots, live continuation episodes); read defensively.
_SOURCE_EXTRA = ("seed", "trunk_steps", "_queue", "_live", "episodes_finished")


def make_collector(
    cfg: DictConfig, env: EnvBase, policy: TensorDictModuleBase, seed: int
) -> BaseCollector:
    """The collector of ``cfg.algo.name`` over ``env`` (which it owns and closes).

    The collector runs without a frame budget: the trainer stops it, counting trunk
    steps too.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.branching import make_branch_env
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> cfg = OmegaConf.create({"algo": {"name": "grpo_branch", "group_size": 2,
        ...     "roots": "trunk", "select": "best"}, "rollout": {"horizon": 2,
        ...     "groups_per_batch": 1, "decision_interval": 2}})
        >>> collector = make_collector(cfg, make_branch_env("merge-v0", 1, backend="single"),
        ...                            RandomPolicy(seed=0), seed=0)
        >>> next(iter(collector)).batch_size
        torch.Size([1, 2, 2])
        >>> collector.shutdown()
    """
    algo, rollout = cfg.algo, cfg.rollout
    name = str(algo.name)
    if name in ("grpo_branch", "grpo_episode"):
        roots = str(algo.roots)
        return GroupCollector(
            env,
            policy,
            group_size=int(algo.group_size),
            horizon=int(rollout.horizon),
            groups_per_batch=int(rollout.groups_per_batch),
            total_frames=-1,
            roots="continue" if roots == "continuation" else roots,
            decision_interval=int(rollout.decision_interval),
            select=str(algo.select),
            seed=seed,
        )
    env.set_seed(seed)
    return Collector(
        env,
        policy,
        frames_per_batch=int(rollout.frames_per_batch),
        total_frames=-1,
        auto_register_policy_transforms=False,
    )


def env_frames(collector: BaseCollector) -> int:
    """Env steps simulated so far: collected frames plus GRPO trunk steps."""
    frames = int(getattr(collector, "frames", getattr(collector, "_frames", 0)))
    return frames + int(getattr(collector, "trunk_frames", 0))


def collector_state(collector: BaseCollector) -> dict[str, Any]:
    """The collector's exact position (see the module docstring)."""
    if isinstance(collector, GroupCollector):
        source = collector.root_source
        extra = {k: getattr(source, k) for k in _SOURCE_EXTRA if hasattr(source, k)}
        extra = {k: v.clone() if hasattr(v, "clone") else v for k, v in extra.items()}
        return {"kind": "group", "state": collector.state_dict(), "source": extra}
    carrier = collector._carrier  # the collector's live step (TorchRL's "carrier")
    return {
        "kind": "torchrl",
        "frames": collector._frames,
        "iter": collector._iter,
        "traj_pool": collector._traj_pool.state_dict(),
        "carrier": carrier.clone(),
    }


def load_collector_state(collector: BaseCollector, state: dict[str, Any]) -> None:
    """Put a freshly built collector back where :func:`collector_state` was taken."""
    if isinstance(collector, GroupCollector):
        if state["kind"] != "group":
            raise ValueError("this checkpoint was written by a PPO run")
        collector.load_state_dict(state["state"])
        for key, value in state["source"].items():
            setattr(collector.root_source, key, value)
        return
    if state["kind"] != "torchrl":
        raise ValueError("this checkpoint was written by a GRPO run")
    carrier = state["carrier"]
    env = collector.env
    # Restore every worker's simulator (traffic, RNG, time) to the saved step.
    env.reset(
        TensorDict({STATE: carrier.get(STATE).clone()}, batch_size=env.batch_size),
        set_state=True,
    )
    collector._carrier = carrier.clone()
    collector._frames = int(state["frames"])
    collector._iter = int(state["iter"])
    collector._traj_pool.load_state_dict(state["traj_pool"])
