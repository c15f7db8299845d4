"""Builder of the collectors: ``GroupCollector`` for GRPO, TorchRL's ``Collector`` for PPO.

Also saves and restores a collector's exact position for checkpoints:

- GRPO: the collector's ``state_dict()``: its counters and its root source's
  ``state_dict()`` (seed chain, pending trunk decision points, live episodes).
- PPO: the collector's counters, its carrier (the current observation of every
  worker) and every worker's simulator state, read from the carrier: PPO workers
  write their state after each step (``return_state=True``), so a resumed run
  continues the same episodes, mid-episode.
- GRPO on Ray (``rollout=ray``): the learner's counters and every actor's
  snapshot (see :class:`~torchrl_grpo.distributed.RayGroupCollector`).
"""

from __future__ import annotations

import copy
from typing import Any

from omegaconf import DictConfig
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import BaseCollector, Collector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.group_collector import GroupCollector
from torchrl_grpo.branching.keys import STATE
from torchrl_grpo.branching.roots import TrunkRoots
from torchrl_grpo.distributed.ray_collector import RayGroupCollector
from torchrl_grpo.modules.greedy_tail import GreedyTail
from torchrl_grpo.training.group_schemas import collects_on_ray
from torchrl_grpo.training.ray_rollout import make_ray_collector

__all__ = [
    "collector_state",
    "env_frames",
    "world_steps",
    "load_collector_state",
    "make_collector",
    "trunk_schedule",
]

# Checkpoints written before root sources had a complete state_dict() kept the missing
# part apart ("source"), under the sources' attribute names: their state_dict() keys.
_LEGACY_SOURCE_KEYS = {"_queue": "queue", "_live": "live"}


def make_collector(
    cfg: DictConfig,
    env: EnvBase | None,
    policy: TensorDictModuleBase,
    seed: int,
    tail_policy: TensorDictModuleBase | None = None,
    trunk_stagger: int = 0,
    trunk_max_steps: int | None = None,
    trunk_min_steps: int = 0,
    trunk_exploration: ExplorationType = ExplorationType.RANDOM,
    learner_branches: int | None = None,
) -> BaseCollector:
    """The collector of ``cfg.algo.name`` over ``env`` (which it owns and closes).

    The collector runs without a frame budget: the trainer stops it, counting trunk
    steps too. With ``rollout=ray`` the envs are built in the Ray actors:
    pass ``env=None`` (a given env is closed). ``tail_policy`` is the actor greedy
    tails follow: a scripted base policy (``algo.tail_policy``; trunks follow
    ``policy``), or a lagging copy of ``policy`` (greedy trunks follow it too; the
    experimental ``algo.tail_sync_batches``). Default: ``policy``. ``trunk_stagger``
    spreads live trunks' first episodes over that many steps
    (:class:`~torchrl_grpo.branching.roots.TrunkRoots`' ``stagger``;
    ``rollout.stagger_trunks``); ``trunk_max_steps`` ends trunks at that
    episode step, ``trunk_min_steps`` starts their decision points at that step (the
    experimental ``rollout.full_horizon_roots`` and ``rollout.first_root_step``), and the
    trunks (or the ``Collector``'s worlds) act with ``trunk_exploration`` (the policy
    samples; ``algo=search_distill`` and the experimental ``algo.trunk=greedy`` act
    deterministically). ``learner_branches``: only the
    branches below it take ``algo.tail_learner_steps``
    (:class:`~torchrl_grpo.modules.GreedyTail`'s; ``None``: every branch).

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
    if algo.get("roots") is not None:  # GRPO: groups of branches from roots
        roots = str(algo.roots)
        learner = policy
        explore_steps = algo.get("explore_steps")
        if explore_steps is not None:
            first_action = str(algo.get("first_action", "sample"))
            policy = GreedyTail(
                policy,
                int(explore_steps),
                first_action=first_action,
                tail_policy=tail_policy,
                learner_steps=int(algo.get("tail_learner_steps", 0)),
                learner_branches=learner_branches,
            )
        # A scripted base tail scores actions; the trunks still follow the learner, so
        # that its decision points are the states the learner visits (as in DAgger).
        base_tail = str(algo.get("tail_policy", "learner")) != "learner"
        source = "continue" if roots == "continuation" else roots
        live = bool(rollout.get("live_trunks", False))
        bounded = trunk_max_steps is not None or trunk_min_steps > 0
        sampled = trunk_exploration == ExplorationType.RANDOM
        if roots == "trunk" and (not sampled or base_tail or live or bounded):
            source = TrunkRoots(
                int(rollout.decision_interval),
                exploration_type=trunk_exploration,
                policy=learner if base_tail else None,
                max_steps=trunk_max_steps,
                min_steps=trunk_min_steps,
                live=live,
                stagger=trunk_stagger,
            )
        if collects_on_ray(rollout):
            if env is not None:
                env.close()
            return make_ray_collector(cfg, policy, source, seed)
        return GroupCollector(
            env,
            policy,
            group_size=int(algo.group_size),
            horizon=int(rollout.horizon),
            groups_per_batch=int(rollout.groups_per_batch),
            total_frames=-1,
            roots=source,
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
        exploration_type=trunk_exploration,
    )


def trunk_schedule(rollout: DictConfig, step_limit: int) -> tuple[int, int, int | None]:
    """The ``trunk_stagger``, ``trunk_min_steps`` and ``trunk_max_steps`` of :func:`make_collector`.

    ``rollout.stagger_trunks`` spreads the live trunks over an episode's ``step_limit``
    steps; decision points start at the episode's first step, and trunks run to its end.
    (The experimental ``algo=grpo_lab`` bounds them too: ``rollout.first_root_step``,
    ``rollout.full_horizon_roots``.)

    Example:
        >>> from omegaconf import OmegaConf
        >>> trunk_schedule(OmegaConf.create({"horizon": 8, "stagger_trunks": True}), 30)
        (30, 0, None)
    """
    return (step_limit if rollout.get("stagger_trunks") else 0), 0, None


def env_frames(collector: BaseCollector) -> int:
    """Env steps simulated so far: collected frames plus GRPO trunk steps.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> collector = GroupCollector(HighwayEnv("merge-v0"), ConstantActionPolicy("IDLE"),
        ...                            group_size=2, horizon=2, groups_per_batch=1,
        ...                            roots="trunk", seed=0)
        >>> _ = next(iter(collector))
        >>> collector.frames, collector.trunk_frames, env_frames(collector)
        (4, 4, 8)
        >>> collector.shutdown()
    """
    frames = int(getattr(collector, "frames", getattr(collector, "_frames", 0)))
    return frames + int(getattr(collector, "trunk_frames", 0))


def world_steps(collector: BaseCollector) -> int | None:
    """Worlds the collector's batched simulator has stepped, masked rows included, or ``None``.

    A frame is a step of a world that is not masked out; a batched simulator steps
    every row of its batch, so its throughput counts those too.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> collector = GroupCollector(HighwayEnv("merge-v0"), ConstantActionPolicy("IDLE"),
        ...                            group_size=2, horizon=2, groups_per_batch=1, seed=0)
        >>> world_steps(collector) is None
        True
    """
    steps = getattr(getattr(collector, "env", None), "world_steps", None)
    # ParallelEnv answers any attribute with a dispatcher to its workers: only an int counts.
    return steps if isinstance(steps, int) else None


def collector_state(collector: BaseCollector) -> dict[str, Any]:
    """The collector's exact position (see the module docstring).

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> collector = GroupCollector(HighwayEnv("merge-v0"), ConstantActionPolicy("IDLE"),
        ...                            group_size=2, horizon=2, groups_per_batch=1, seed=0)
        >>> _ = next(iter(collector))
        >>> state = collector_state(collector)
        >>> state["kind"], state["state"]["frames"], state["state"]["next_group_id"]
        ('group', 4, 1)
        >>> collector.shutdown()
    """
    if isinstance(collector, RayGroupCollector):
        return {"kind": "ray", "state": collector.state_dict()}
    if isinstance(collector, GroupCollector):
        # A copy: the root source's tensors are its own (state_dict() does not copy).
        return {"kind": "group", "state": copy.deepcopy(collector.state_dict())}
    carrier = collector._carrier  # the collector's live step (TorchRL's "carrier")
    return {
        "kind": "torchrl",
        "frames": collector._frames,
        "iter": collector._iter,
        "traj_pool": collector._traj_pool.state_dict(),
        "carrier": carrier.clone(),
    }


def load_collector_state(collector: BaseCollector, state: dict[str, Any]) -> None:
    """Put a freshly built collector back where :func:`collector_state` was taken.

    Example:
        >>> import torch
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> def build():
        ...     return GroupCollector(HighwayEnv("merge-v0"), ConstantActionPolicy("IDLE"),
        ...                           group_size=2, horizon=2, groups_per_batch=1, seed=0)
        >>> collector = build()
        >>> _ = next(iter(collector))
        >>> state = collector_state(collector)
        >>> expected = next(iter(collector))  # the batch after the checkpoint
        >>> resumed = build()
        >>> load_collector_state(resumed, state)
        >>> batch = next(iter(resumed))
        >>> batch["group_id"][0, 0, 0].item(), torch.equal(batch["observation"],
        ...                                                expected["observation"])
        (1, True)
        >>> collector.shutdown(), resumed.shutdown()
        (None, None)
    """
    if isinstance(collector, RayGroupCollector):
        if state["kind"] != "ray":
            raise ValueError("this checkpoint was not written with rollout=ray")
        collector.load_state_dict(state["state"])
        return
    if isinstance(collector, GroupCollector):
        if state["kind"] != "group":
            raise ValueError("this checkpoint was written by a PPO run")
        collector.load_state_dict(state["state"])
        if "source" in state:  # written before root sources had a complete state_dict()
            legacy = {_LEGACY_SOURCE_KEYS.get(k, k): v for k, v in state["source"].items()}
            collector.root_source.load_state_dict(legacy)
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
