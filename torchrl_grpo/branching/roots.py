"""Root sources: where the groups of each batch of a :class:`GroupCollector` start.

A :class:`RootSource` supplies roots (see :mod:`~torchrl_grpo.branching.root_builders`)
batch after batch: fresh episode starts (:class:`EpisodeStartRoots`), decision points
along policy trunks (:class:`TrunkRoots`), stored roots (:class:`StoredRoots`), or the
live episodes of a multi-turn collection
(:class:`~torchrl_grpo.branching.ContinuationRoots`). Its ``state_dict`` holds all it
needs to continue exactly, for checkpoints and fault recovery.

The root builders are re-exported here, where they were defined before.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.dispatch import run_on
from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.keys import ROOT_STEP, STATE
from torchrl_grpo.branching.rollout_rows import Policy
from torchrl_grpo.branching.root_builders import (
    as_roots,
    make_roots,
    reset_roots,
    reset_states,
    roots_from_trajectories,
    run_trunks,
    trunk_roots,
)

__all__ = [
    "EpisodeStartRoots",
    "RootSource",
    "StoredRoots",
    "TrunkRoots",
    "as_roots",
    "make_roots",
    "reset_roots",
    "roots_from_trajectories",
    "trunk_roots",
]


class RootSource(ABC):
    """Supplies the roots of each batch of a :class:`~torchrl_grpo.branching.GroupCollector`.

    Subclass it to branch from your own states. A source that continues episodes
    from the collected branches sets ``needs_final_states`` and receives every batch
    through :meth:`observe`. A source with state of its own extends
    :meth:`state_dict` and :meth:`load_state_dict`, so that a checkpoint (or a Ray
    actor that replaces a dead one) continues it exactly.

    Example:
        >>> from torchrl_grpo.branching import GroupCollector
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> class FixedRoot(RootSource):  # every group branches from the same state
        ...     def __init__(self, state):
        ...         self.state = state
        ...     def next_roots(self, env, policy, num_roots):
        ...         return make_roots([self.state] * num_roots, root_step=0)
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> source = FixedRoot(env.get_state())
        >>> with GroupCollector(env, RandomPolicy(seed=0), group_size=2, horizon=2,
        ...                     groups_per_batch=1, total_frames=8, roots=source) as collector:
        ...     for batch in collector:
        ...         print(batch.batch_size, batch["group_id"][:, 0, 0].tolist())
        torch.Size([1, 2, 2]) [0]
        torch.Size([1, 2, 2]) [1]
    """

    needs_final_states: bool = False
    seed: int | None = None

    @abstractmethod
    def next_roots(self, env: EnvBase, policy: Policy, num_roots: int) -> TensorDict:
        """Return roots ``[num_roots]`` (fewer only when the source is exhausted; empty: done)."""

    def observe(  # noqa: B027 - optional hook, empty by design
        self,
        data: TensorDictBase,
        final_states: TensorDictBase | None,
        ended: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> None:
        """See the batch just collected (``[R, G, T]``) and each branch's final state."""

    def set_seed(self, seed: int) -> None:
        """Seed the episodes this source resets (``None`` seeds: torch's generator)."""
        self.seed = int(seed)

    def fresh_roots(self, env: EnvBase, num_roots: int) -> TensorDict:
        """New episode starts, continuing this source's seed sequence."""
        roots, next_seed = reset_states(env, num_roots, self.seed)
        if self.seed is not None:
            self.seed = next_seed
        return roots

    def state_dict(self) -> dict[str, Any]:
        """All the source needs to continue exactly; here, its seed chain (``"seed"``).

        Tensors are the source's own, not copies (as with ``nn.Module.state_dict``):
        the source replaces them rather than writing into them, so a state dict stays
        valid, but copy it (``copy.deepcopy``) to keep it where it may be modified.
        """
        return {"seed": self.seed}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        An entry missing from ``state_dict`` (a state saved by an older version, which
        did not record it) leaves that part of the source as it is.
        """
        if "seed" in state_dict:
            seed = state_dict["seed"]
            self.seed = None if seed is None else int(seed)


class EpisodeStartRoots(RootSource):
    """Episode-level groups: every batch branches from fresh resets.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> source = EpisodeStartRoots()
        >>> source.set_seed(0)
        >>> source.next_roots(HighwayEnv("merge-v0"), None, 2).batch_size
        torch.Size([2])
    """

    def next_roots(self, env: EnvBase, policy: Policy, num_roots: int) -> TensorDict:
        """Reset ``env`` to ``num_roots`` new episodes."""
        return self.fresh_roots(env, num_roots)


class TrunkRoots(RootSource):
    """Vine-style groups: decision points every ``every`` steps along policy trunks.

    Trunks are run (with the current policy) whenever the queue of decision points
    runs short, W at a time; a batch may mix decision points of several trunks.

    Args:
        every: K, the number of steps between decision points.
        max_steps: stop trunks at this episode step.
        exploration_type: how the policy acts on the trunks.
        policy: the policy the trunks follow; ``None``: the collector's (the one that
            also acts on the branches). Give the learner here when the branches act
            through a wrapper that should not drive the trunks, e.g. a
            :class:`~torchrl_grpo.modules.GreedyTail` whose tail is a fixed base policy.
        live: keep ``num_roots`` trunks alive between batches and advance each by one
            segment of K steps per batch (an ended trunk is replaced by a new episode),
            so that every batch's decision points come from the current policy. The
            default runs whole trunks, W at a time, and queues their decision points.
        stagger: with ``live``, spread the trunks' first episodes over this many steps
            (the episode length, say): before the first batch, trunk ``i`` of ``n`` runs
            ``i * stagger // n`` steps (whole segments). Without it the trunks start
            together and stay in step, so that each batch holds the decision points of
            one episode step only and the training data cycles with the episode.
            ``0``: no spread.
        min_steps: the episode step of a trunk's first decision point: a new trunk runs
            that many steps first (``0``: from the episode's start).

    Attributes:
        trunk_steps: env steps simulated on trunks so far (not part of any batch).

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> src = TrunkRoots(every=2, max_steps=7)
        >>> env, policy = HighwayEnv("merge-v0", seed=0), ConstantActionPolicy("SLOWER")
        >>> src.set_seed(0)
        >>> src.next_roots(env, policy, 2)["root_step"].tolist()  # a trunk of 8 steps
        [0, 2]
        >>> resumed = TrunkRoots(every=2, max_steps=7)
        >>> resumed.load_state_dict(src.state_dict())  # the seed chain, the queued roots
        >>> resumed.next_roots(env, policy, 2)["root_step"].tolist(), resumed.trunk_steps
        ([4, 6], 8)
    """

    def __init__(
        self,
        every: int,
        *,
        max_steps: int | None = None,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        policy: Policy | None = None,
        live: bool = False,
        stagger: int = 0,
        min_steps: int = 0,
    ) -> None:
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        if stagger < 0:
            raise ValueError(f"stagger must be >= 0, got {stagger}")
        if min_steps < 0 or (max_steps is not None and min_steps >= max_steps):
            raise ValueError(
                f"min_steps must be >= 0 and below max_steps ({max_steps}), got {min_steps}"
            )
        self.every = every
        self.max_steps = max_steps
        self.exploration_type = exploration_type
        self.policy = policy
        self.live = live
        self.stagger = stagger
        self.min_steps = min_steps
        self._queue: TensorDict | None = None
        self.trunk_steps = 0

    def next_roots(self, env: EnvBase, policy: Policy, num_roots: int) -> TensorDict:
        """Pop ``num_roots`` decision points, running new trunks when the queue is short."""
        slots = EnvSlots(env)
        if self.live:
            return self._advance_live(env, slots, policy, num_roots)
        while self._queue is None or self._queue.shape[0] < num_roots:
            starts = self.fresh_roots(env, slots.num_slots)
            new, steps = run_trunks(
                slots,
                policy if self.policy is None else self.policy,
                starts,
                self.every,
                self.max_steps,
                self.exploration_type,
            )
            new = new.exclude("trunk")
            new = new[new.get(ROOT_STEP) >= self.min_steps]
            self.trunk_steps += steps
            self._queue = new if self._queue is None else torch.cat([self._queue, new])
        out, self._queue = self._queue[:num_roots], self._queue[num_roots:]
        return out

    def _advance_live(
        self, env: EnvBase, slots: EnvSlots, policy: Policy, num_roots: int
    ) -> TensorDict:
        """One segment of every live trunk; new episodes for the trunks that ended."""
        live = self._queue
        if live is None or live.shape[0] != num_roots:
            new = self._new_trunks(env, slots, policy, num_roots)
            self._queue = self._spread(env, slots, policy, new)
        else:
            self._queue = self._segment(env, slots, policy, live)
        return self._queue.clone()

    def _spread(
        self, env: EnvBase, slots: EnvSlots, policy: Policy, live: TensorDict
    ) -> TensorDict:
        """Run trunk ``i`` of ``n`` for ``i * stagger // n`` steps, in whole segments."""
        n = live.shape[0]
        segments = torch.arange(n) * (self.stagger // self.every) // max(n, 1)
        for j in range(int(segments.max()) if n else 0):
            rows = segments > j
            live[rows] = self._segment(env, slots, policy, live[rows])
        return live

    def _segment(
        self, env: EnvBase, slots: EnvSlots, policy: Policy, live: TensorDict
    ) -> TensorDict:
        """``live`` advanced by one segment: the trunks still alive, then new episodes."""
        n = live.shape[0]
        kept = self._survivors(slots, policy, live, self.every)
        if kept.shape[0] == n:
            return kept
        new = self._new_trunks(env, slots, policy, n - kept.shape[0])
        return torch.cat([kept, new.to(kept.device)])

    def _new_trunks(self, env: EnvBase, slots: EnvSlots, policy: Policy, n: int) -> TensorDict:
        """``n`` new episodes, run to their first decision point (step ``min_steps``)."""
        if not self.min_steps:
            return self.fresh_roots(env, n)
        ready: list[TensorDict] = []
        # An episode that ends before its first decision point is replaced.
        while (missing := n - sum(r.shape[0] for r in ready)) > 0:
            starts = self.fresh_roots(env, missing)
            ready.append(self._survivors(slots, policy, starts, self.min_steps))
        return torch.cat(ready)

    def _survivors(
        self, slots: EnvSlots, policy: Policy, live: TensorDict, steps: int
    ) -> TensorDict:
        """The trunks of ``live`` that are still running after ``steps`` more steps.

        A trunk drops out when its episode ends on the way or it reaches ``max_steps``.
        """
        n = live.shape[0]
        run = run_on(
            slots,
            policy if self.policy is None else self.policy,
            live.get(STATE),
            steps,
            group_id=torch.arange(n),
            branch=torch.zeros(n, dtype=torch.long),
            root_step=live.get(ROOT_STEP),
            keep="final",
            exploration_type=self.exploration_type,
        )
        self.trunk_steps += int(run.lengths.sum())
        reached = live.get(ROOT_STEP).to(run.lengths.device) + run.lengths
        alive = ~run.ended & (run.lengths == steps)
        if self.max_steps is not None:
            alive &= reached < self.max_steps
        alive = alive.cpu()
        return TensorDict(
            {
                STATE: run.final_states[alive.to(run.final_states.device)],
                ROOT_STEP: reached.cpu()[alive],
            },
            batch_size=[int(alive.sum())],
        )

    def state_dict(self) -> dict[str, Any]:
        """The seed chain, ``trunk_steps`` and the ``"queue"`` of decision points."""
        return {**super().state_dict(), "trunk_steps": self.trunk_steps, "queue": self._queue}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (see :meth:`RootSource.load_state_dict`)."""
        super().load_state_dict(state_dict)
        if "trunk_steps" in state_dict:
            self.trunk_steps = int(state_dict["trunk_steps"])
        if "queue" in state_dict:
            self._queue = state_dict["queue"]


class StoredRoots(RootSource):
    """Branch from given roots, ``num_roots`` at a time, in order.

    Args:
        roots: roots (see :func:`make_roots` / :func:`roots_from_trajectories`).
        cycle: start over at the end instead of stopping.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> src = StoredRoots(reset_roots(HighwayEnv("merge-v0", seed=0), 3))
        >>> [src.next_roots(None, None, 2).shape[0] for _ in range(3)]
        [2, 1, 0]
    """

    def __init__(self, roots: TensorDictBase, *, cycle: bool = False) -> None:
        self.roots = as_roots(roots)
        self.cycle = cycle
        self._pos = 0

    def next_roots(self, env: EnvBase | None, policy: Policy | None, num_roots: int) -> TensorDict:
        """The next ``num_roots`` stored roots."""
        n = self.roots.shape[0]
        if self.cycle:
            idx = (self._pos + torch.arange(num_roots)) % n
            self._pos = (self._pos + num_roots) % n
            return self.roots[idx]
        out = self.roots[self._pos : self._pos + num_roots]
        self._pos += out.shape[0]
        return out

    def state_dict(self) -> dict[str, Any]:
        """The seed chain and the read position (``"pos"``)."""
        return {**super().state_dict(), "pos": self._pos}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (see :meth:`RootSource.load_state_dict`)."""
        super().load_state_dict(state_dict)
        if "pos" in state_dict:
            self._pos = int(state_dict["pos"])
