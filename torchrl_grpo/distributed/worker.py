"""The Ray actor of the Ray backend: one :class:`GroupCollector` and its env workers.

:class:`GroupWorker` is a plain class: :class:`~torchrl_grpo.distributed.RayGroupCollector`
turns it into a Ray actor at run time (``ray.remote(GroupWorker)``), so importing this
module does not need Ray.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torchrl_grpo.branching.group_collector import GroupCollector
from torchrl_grpo.branching.roots import RootSource
from torchrl_grpo.envs.core.errors import SnapshotError

logger = logging.getLogger(__name__)

__all__ = ["GroupResult", "GroupWorker", "WorkerSnapshot", "actor_seed", "shared_root_policy"]

_SEED_MOD = 2**31 - 1  # torch, numpy and TorchRL's env seeding all take it


def actor_seed(seed: int, actor: int) -> int:
    """The seed of actor ``actor`` of a Ray collection seeded with ``seed``.

    Actor 0 gets ``seed`` itself, so one actor reproduces a local
    :class:`~torchrl_grpo.branching.GroupCollector` seeded with ``seed``; the others get
    a seed mixed from ``(seed, actor)`` by numpy's ``SeedSequence`` (unrelated streams).

    Example:
        >>> actor_seed(7, 0), actor_seed(7, 1) == actor_seed(7, 1), actor_seed(7, 1) == 7
        (7, True, False)
    """
    if actor == 0:
        return int(seed)
    words = np.random.SeedSequence([int(seed), int(actor), 0x7261_79]).generate_state(1)
    return int(words[0]) % _SEED_MOD


def shared_root_policy(policy: Any, roots: Any) -> str | None:
    """Which submodule of ``policy`` the root source ``roots`` follows, or ``None``.

    A root source may run its trunks with a policy of its own that is part of the
    collector's policy: the learner inside a :class:`~torchrl_grpo.modules.GreedyTail`
    whose tails are a scripted base policy. Shipping both to a Ray actor copies them
    apart, and the weights the learner sends each batch would then reach the tails'
    wrapper but not the trunks; the actor links them again by this path.

    Example:
        >>> from torchrl_grpo.branching.roots import TrunkRoots
        >>> from torchrl_grpo.modules import GreedyTail, KinematicsMLP, make_discrete_actor
        >>> from torchrl_grpo.modules import RulePolicy
        >>> learner = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
        >>> tails = GreedyTail(learner, 1, first_action="enumerate", tail_policy=RulePolicy())
        >>> shared_root_policy(tails, TrunkRoots(1, policy=learner))
        'policy'
        >>> shared_root_policy(tails, "trunk") is None
        True
    """
    own = getattr(roots, "policy", None)
    if own is None or not isinstance(policy, torch.nn.Module):
        return None
    for name, module in policy.named_modules():
        if module is own:
            return name
    return None


@dataclass
class WorkerSnapshot:
    """Everything a fresh actor needs to continue exactly where another one stood.

    Attributes:
        collector: ``GroupCollector.state_dict()`` (frames, batches, next group id,
            selection generator, the root source's ``state_dict()``: its seed chain,
            pending trunk decision points or live episodes).
        root_source: a copy of the root source (exact even for a source of your own
            whose ``state_dict`` is not complete).
        torch_rng: the actor's global torch generator, from which the policy samples.

    Example:
        >>> import copy, functools
        >>> from torchrl_grpo.branching import make_branch_env
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> def build(seed):  # no Ray needed: GroupWorker is a plain class
        ...     env_factory = functools.partial(make_branch_env, "merge-v0", 1, backend="single")
        ...     return GroupWorker(env_factory, ConstantActionPolicy("IDLE"),
        ...                        dict(group_size=2, horizon=2, groups_per_batch=1),
        ...                        seed=seed, num_threads=None)
        >>> worker, replacement = build(0), build(1)
        >>> snapshot = worker.collect(None, first_group_id=0).snapshot
        >>> snapshot.collector["frames"]
        4
        >>> replacement.restore(copy.deepcopy(snapshot))  # as if shipped to another actor
        >>> a = worker.collect(None, first_group_id=1).data
        >>> b = replacement.collect(None, first_group_id=1).data
        >>> torch.equal(a["observation"], b["observation"])
        True
        >>> worker.close(), replacement.close()
        (None, None)
    """

    collector: dict[str, Any]
    root_source: RootSource
    torch_rng: torch.Tensor


@dataclass
class GroupResult:
    """What an actor returns for one batch.

    Attributes:
        data: the ``[R_a, G, T]`` groups (``None`` when the roots ran out).
        snapshot: the actor's state after this batch (where a replacement restarts).
        trunk_frames: trunk steps the actor simulated so far (``roots="trunk"``).

    Example:
        >>> import functools
        >>> from torchrl_grpo.branching import make_branch_env
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> env_factory = functools.partial(make_branch_env, "merge-v0", 1, backend="single")
        >>> worker = GroupWorker(env_factory, ConstantActionPolicy("IDLE"),  # no Ray needed
        ...                      dict(group_size=2, horizon=2, groups_per_batch=1, roots="trunk"),
        ...                      seed=0, num_threads=None)
        >>> result = worker.collect(None, first_group_id=0)
        >>> result.data.batch_size, result.trunk_frames, type(result.snapshot).__name__
        (torch.Size([1, 2, 2]), 4, 'WorkerSnapshot')
        >>> worker.close()
    """

    data: TensorDictBase | None
    snapshot: WorkerSnapshot
    trunk_frames: int


class GroupWorker:
    """Owns one :class:`~torchrl_grpo.branching.GroupCollector` inside a Ray actor.

    The actor seeds torch's global generator with ``seed`` right after building its
    collector (also seeded with ``seed``): the policy samples from that generator. So a
    local ``GroupCollector(env, policy, seed=s, ...)`` followed by ``torch.manual_seed(s)``
    yields bitwise the same batches as an actor built with seed ``s``.

    Args:
        env_factory: a picklable callable building the branch env, e.g.
            ``functools.partial(make_branch_env, "merge-v0", 2)``.
        policy: the policy (a copy is shipped to the actor).
        collector_kwargs: the other :class:`GroupCollector` arguments.
        seed: this actor's seed (see :func:`actor_seed`).
        num_threads: torch threads of the actor (1: the env workers need the cores).
        root_policy: the submodule of ``policy`` the root source's trunks follow
            (:func:`shared_root_policy`); linked again here, and after every restore.

    Example:
        >>> import functools
        >>> from torchrl_grpo.branching import make_branch_env
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> worker = GroupWorker(functools.partial(make_branch_env, "merge-v0", 1,
        ...                      backend="single"), RandomPolicy(seed=0),
        ...                      dict(group_size=2, horizon=2, groups_per_batch=1), seed=0)
        >>> worker.collect(None, first_group_id=5).data["group_id"][0, 0, 0].item()
        5
        >>> worker.close()
    """

    def __init__(
        self,
        env_factory: Callable[[], EnvBase],
        policy: Any,
        collector_kwargs: dict[str, Any],
        seed: int,
        num_threads: int | None = 1,
        root_policy: str | None = None,
    ) -> None:
        if num_threads is not None:
            torch.set_num_threads(int(num_threads))
        self.collector = GroupCollector(
            env_factory, policy, total_frames=-1, seed=int(seed), **collector_kwargs
        )
        self.root_policy = root_policy
        self._link_root_policy()
        torch.manual_seed(int(seed))
        self._iterator = None

    def _link_root_policy(self) -> None:
        # The trunks follow the collector's own submodule, which receives the weights.
        if self.root_policy is not None:
            self.collector.root_source.policy = self.collector.policy.get_submodule(
                self.root_policy
            )

    def pid(self) -> int:
        """The actor's process id (tests kill it)."""
        return os.getpid()

    def snapshot(self) -> WorkerSnapshot:
        """The actor's current state (see :class:`WorkerSnapshot`)."""
        return WorkerSnapshot(
            collector=self.collector.state_dict(),
            root_source=self.collector.root_source,
            torch_rng=torch.get_rng_state(),
        )

    def restore(self, snapshot: WorkerSnapshot) -> None:
        """Continue from ``snapshot`` (taken in another actor, usually a dead one)."""
        # The snapshot was unpickled in this process: its root source is this actor's own.
        self.collector.root_source = snapshot.root_source
        self._link_root_policy()  # the snapshot's copy of it holds old weights
        self.collector.load_state_dict(snapshot.collector)
        torch.set_rng_state(snapshot.torch_rng)

    def set_seed(self, seed: int) -> WorkerSnapshot:
        """Reseed the collector and torch's generator as a fresh actor would be."""
        self.collector.set_seed(int(seed))
        torch.manual_seed(int(seed))
        return self.snapshot()

    def collect(
        self, weights: TensorDictBase | None, first_group_id: int, keep_snapshot: bool = True
    ) -> GroupResult:
        """Load ``weights``, collect one batch whose group ids start at ``first_group_id``.

        The ids are assigned by the learner, so that they are unique over all actors,
        and set before the batch because ``rng="per_branch"`` seeds depend on them.
        A root state the env refuses raises its :class:`~torchrl_grpo.envs.SnapshotError`
        and leaves the actor usable (the next call goes on with the next roots); any
        other error shuts the collector down.
        """
        if weights is not None:
            self.collector.update_policy_weights_(weights)
        state = self.collector.state_dict()
        state["next_group_id"] = int(first_group_id)
        self.collector.load_state_dict(state)
        if self._iterator is None:
            self._iterator = self.collector.iterator()
        try:
            data = next(self._iterator)
        except StopIteration:
            data = None
        except SnapshotError:
            # A refused state reached no env (its workers live on) and the root source
            # has moved past it: the actor stays usable, its next batch iterates afresh.
            self._iterator = None
            raise
        except BaseException:
            self.collector.shutdown()  # as iterating the collector itself would
            raise
        snapshot = self.snapshot() if keep_snapshot else None
        return GroupResult(data=data, snapshot=snapshot, trunk_frames=self.collector.trunk_frames)

    def close(self) -> None:
        """Shut the collector and its env workers down."""
        self.collector.shutdown()
