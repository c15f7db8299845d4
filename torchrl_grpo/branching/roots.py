"""Where groups start: episode starts, decision points along a trunk, stored trajectories.

A *roots* tensordict has batch size ``[R]`` and holds, per root, the ``"state"`` to
branch from (a :meth:`~torchrl_grpo.envs.SnapshotEnv.get_state` state) and its
``"root_step"`` (how many steps into its episode it is). Every function here
returns one; :func:`~torchrl_grpo.branching.branch_rollout` takes one.

The :class:`RootSource` classes supply roots batch after batch to a
:class:`~torchrl_grpo.branching.GroupCollector`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching._engine import Policy, run_branches
from torchrl_grpo.branching._slots import EnvSlots
from torchrl_grpo.branching.keys import MASK, ROOT_STEP, STATE, STEP_COUNT

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


def make_roots(
    states: TensorDictBase | Sequence[TensorDictBase], root_step: int | torch.Tensor = 0
) -> TensorDict:
    """Bundle states into a roots tensordict.

    Args:
        states: one state, a list of states, or states stacked to ``[R]``.
        root_step: the episode step of each state (an int for all, or ``[R]``).

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> state = HighwayEnv("merge-v0", seed=0).get_state()
        >>> roots = make_roots([state, state], root_step=3)
        >>> roots.batch_size, roots["root_step"].tolist()
        (torch.Size([2]), [3, 3])
    """
    if not isinstance(states, TensorDictBase):
        states = torch.stack(list(states))
    elif states.batch_dims == 0:
        states = states.unsqueeze(0)
    if states.batch_dims != 1:
        raise ValueError(f"root states must have batch size [R], got {tuple(states.batch_size)}")
    n = states.shape[0]
    steps = torch.as_tensor(root_step, dtype=torch.long).expand(n).clone()
    return TensorDict({STATE: states, ROOT_STEP: steps}, batch_size=[n])


def as_roots(roots: TensorDictBase | Sequence[TensorDictBase]) -> TensorDict:
    """Accept roots from :func:`make_roots`, a bare state, or states; return roots ``[R]``.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> as_roots(HighwayEnv("merge-v0", seed=0).get_state()).batch_size
        torch.Size([1])
    """
    if isinstance(roots, TensorDictBase) and STATE in roots.keys():
        if roots.batch_dims == 0:
            roots = roots.unsqueeze(0)
        if roots.batch_dims != 1:
            raise ValueError(f"roots must have batch size [R], got {tuple(roots.batch_size)}")
        if ROOT_STEP not in roots.keys():
            roots = roots.clone(False)
            roots.set(ROOT_STEP, torch.zeros(roots.shape[0], dtype=torch.long))
        return roots
    return make_roots(roots)


def _fresh_states(slots: EnvSlots) -> TensorDictBase:
    """Reset every slot to a new episode and return the ``[W]`` start states."""
    out = slots.env.reset()
    # A fresh reset of a SnapshotEnv writes its state; a batched env only returns it
    # from workers built with return_state=True.
    if slots.has_state or (not slots.batched and STATE in out.keys()):
        states = out.get(STATE)
        return states if slots.batched else states.unsqueeze(0)
    return slots._read_all_states()


def draw_seed() -> int:
    """A seed from torch's global generator (reproducible under ``torch.manual_seed``)."""
    return int(torch.randint(0, 2**31 - 1, ()))


def reset_states(env: EnvBase, num_roots: int, seed: int | None) -> tuple[TensorDict, int]:
    """``num_roots`` fresh episode starts, and the seed that continues the sequence."""
    if num_roots < 1:
        raise ValueError(f"num_roots must be >= 1, got {num_roots}")
    slots = EnvSlots(env)
    seed = draw_seed() if seed is None else int(seed)
    chunks = []
    while sum(c.shape[0] for c in chunks) < num_roots:
        # Seed every reset: a restore overwrites a worker's generator, so without a new
        # seed a worker would start the same episode again after every branch.
        seed = env.set_seed(seed)
        chunks.append(_fresh_states(slots))
    return make_roots(torch.cat(chunks)[:num_roots].clone()), int(seed)


def reset_roots(env: EnvBase, num_roots: int, *, seed: int | None = None) -> TensorDict:
    """Roots at episode starts: ``num_roots`` fresh resets of ``env`` (source (a)).

    A batched env gives W episodes per reset. All G branches of a group then start
    from the same reset, which makes the group an episode-level group.

    The env is seeded (``env.set_seed``) before every reset: restoring a state also
    restores the simulator's generator, so after branching, an unseeded reset would
    replay the episode that followed the root's. ``seed=None`` draws the seed from
    torch's global generator (reproducible under ``torch.manual_seed``).

    Args:
        env: the env to reset.
        num_roots: how many episode starts.
        seed: the seed of the first reset (TorchRL's seed chain continues from it).

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> roots = reset_roots(HighwayEnv("merge-v0"), 2, seed=0)
        >>> roots.batch_size, roots["root_step"].tolist()
        (torch.Size([2]), [0, 0])
    """
    return reset_states(env, num_roots, seed)[0]


def _trunk_roots(
    slots: EnvSlots,
    policy: Policy,
    starts: TensorDict,
    every: int,
    max_steps: int | None,
    exploration_type: ExplorationType,
) -> tuple[TensorDict, int]:
    """Decision points of trunks from ``starts``, and the number of trunk steps taken."""
    n_trunks = starts.shape[0]
    cur = starts.clone(False).set("trunk", torch.arange(n_trunks))
    found = [cur]
    steps_taken = 0
    while cur.shape[0]:
        run = run_branches(
            slots,
            policy,
            cur.get(STATE),
            every,
            group_id=cur.get("trunk"),
            branch=torch.zeros(cur.shape[0], dtype=torch.long),
            root_step=cur.get(ROOT_STEP),
            keep="final",
            exploration_type=exploration_type,
        )
        steps_taken += int(run.lengths.sum())
        # A decision point needs a live episode after a full segment.
        alive = ~run.ended & (run.lengths == every)
        steps = cur.get(ROOT_STEP) + run.lengths
        if max_steps is not None:
            alive &= steps < max_steps
        cur = TensorDict(
            {STATE: run.final_states[alive], ROOT_STEP: steps[alive], "trunk": cur["trunk"][alive]},
            batch_size=[int(alive.sum())],
        )
        found.append(cur)
    roots = torch.cat(found)
    order = torch.argsort(roots.get("trunk") * (1 << 32) + roots.get(ROOT_STEP))
    return roots[order], steps_taken


def trunk_roots(
    env: EnvBase,
    policy: Policy,
    every: int,
    *,
    num_trunks: int = 1,
    starts: TensorDictBase | None = None,
    max_steps: int | None = None,
    seed: int | None = None,
    exploration_type: ExplorationType = ExplorationType.RANDOM,
) -> TensorDict:
    """Roots at decision points every ``every`` steps along policy trunks (source (b)).

    Runs ``num_trunks`` trunks of ``policy`` (W at a time on a batched env) from
    fresh resets, or from ``starts``, to the end of their episodes, and returns the
    state at steps 0, K, 2K, ... of each trunk (vine-style: one group per decision
    point). The result has an extra ``"trunk"`` entry (which trunk each root is on)
    and is sorted by trunk, then step.

    Args:
        env: the env that runs the trunks.
        policy: the trunk's policy.
        every: K, the number of steps between decision points.
        num_trunks: trunks to run when ``starts`` is not given.
        starts: roots to start the trunks from (default: ``num_trunks`` resets).
        max_steps: stop a trunk at this episode step (default: its episode's end).
        seed: seed of the resets (see :func:`reset_roots`).
        exploration_type: how the policy acts on the trunk.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> env = HighwayEnv("highway-fast-v0")
        >>> policy = ConstantActionPolicy("IDLE")
        >>> roots = trunk_roots(env, policy, every=2, max_steps=5, seed=0)
        >>> roots["root_step"].tolist()
        [0, 2, 4]
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    slots = EnvSlots(env)
    if starts is None:
        starts = reset_roots(env, num_trunks, seed=seed)
    else:
        starts = as_roots(starts)
        slots.check_states(starts.get(STATE))
    starts = starts.select(STATE, ROOT_STEP)
    return _trunk_roots(slots, policy, starts, every, max_steps, exploration_type)[0]


def roots_from_trajectories(
    data: TensorDictBase,
    *,
    every: int = 1,
    state_key: NestedKey | None = None,
) -> TensorDict:
    """Roots from stored trajectories that carry states (source (c)).

    The trajectories must carry the state after each step, ``("next", state_key)``:
    collect them with ``HighwayEnv(..., return_state=True)``, whose ``"state"``
    crosses ``ParallelEnv`` workers and collectors like any observation. Every state
    whose episode step is a multiple of ``every`` becomes a root: the state after
    each valid, non-final step, and the episode's start state (the root-level
    ``"state"``) where a trajectory starts an episode.

    The episode step is read from ``"step_count"`` when present (TorchRL's
    :class:`~torchrl.envs.StepCounter`), otherwise counted from the start of each
    trajectory and from every ``("next", "done")``: trajectories must then start at
    an episode start. Masked steps (``"mask"`` or ``("collector", "mask")`` is
    ``False``) are skipped.

    Args:
        data: trajectories with time as the last batch dimension (``[T]``, ``[B, T]``).
        every: keep the states whose episode step is a multiple of this.
        state_key: the state entry (default: ``"state"``).

    Returns:
        Roots sorted by trajectory, then step.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> env = HighwayEnv("merge-v0", seed=0, return_state=True)
        >>> data = env.rollout(5, ConstantActionPolicy("SLOWER"))  # no crash: 5 steps
        >>> roots_from_trajectories(data, every=2)["root_step"].tolist()
        [0, 2, 4]
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if data.batch_dims < 1:
        raise ValueError("data must have a time dimension (batch size [..., T])")
    state_key = STATE if state_key is None else state_key
    if ("next", state_key) not in data.keys(True):
        raise KeyError(
            f"the trajectories hold no ('next', {state_key!r}) entries: collect them with "
            "HighwayEnv(..., return_state=True)"
        )
    flat = data.reshape(-1, data.shape[-1])
    if STEP_COUNT in flat.keys():
        step = flat.get(STEP_COUNT).reshape(flat.shape)
    else:
        step = _steps_since_reset(flat.get(("next", "done")).reshape(flat.shape))
    valid = torch.ones(flat.shape, dtype=torch.bool)
    for mask_key in (MASK, ("collector", "mask")):
        if mask_key in flat.keys(True):
            valid &= flat.get(mask_key).reshape(flat.shape)
    done = flat.get(("next", "done")).reshape(flat.shape)
    starts = valid & (step == 0) & (state_key in flat.keys())
    after = valid & ~done & ((step + 1) % every == 0)
    states = torch.cat([flat.get(state_key)[starts], flat.get(("next", state_key))[after]])
    steps = torch.cat([step[starts], step[after] + 1])
    # Sort by (trajectory, time): a start precedes the states after its own steps.
    rows = torch.arange(flat.shape[0]).unsqueeze(-1).expand(flat.shape)
    order = torch.argsort(
        torch.cat([rows[starts], rows[after]]) * (1 << 32)
        + torch.cat([2 * torch.nonzero(starts)[:, 1], 2 * torch.nonzero(after)[:, 1] + 1])
    )
    return make_roots(states[order].clone(), steps[order])


def _steps_since_reset(done: torch.Tensor) -> torch.Tensor:
    steps = torch.zeros(done.shape, dtype=torch.long)
    for t in range(1, done.shape[-1]):
        steps[:, t] = torch.where(done[:, t - 1], 0, steps[:, t - 1] + 1)
    return steps


class RootSource(ABC):
    """Supplies the roots of each batch of a :class:`~torchrl_grpo.branching.GroupCollector`.

    Subclass it to branch from your own states. A source that continues episodes
    from the collected branches sets ``needs_final_states`` and receives every batch
    through :meth:`observe`.

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

    def state_dict(self) -> dict:
        """Counters to checkpoint (none by default)."""
        return {}

    def load_state_dict(self, state_dict: dict) -> None:  # noqa: B027 - optional hook
        """Restore :meth:`state_dict`."""


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

    Attributes:
        trunk_steps: env steps simulated on trunks so far (not part of any batch).

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> src = TrunkRoots(every=3, max_steps=7)
        >>> env, policy = HighwayEnv("merge-v0", seed=0), ConstantActionPolicy("IDLE")
        >>> src.set_seed(0)
        >>> src.next_roots(env, policy, 2)["root_step"].tolist()
        [0, 3]
    """

    def __init__(
        self,
        every: int,
        *,
        max_steps: int | None = None,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        policy: Policy | None = None,
    ) -> None:
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.every = every
        self.max_steps = max_steps
        self.exploration_type = exploration_type
        self.policy = policy
        self._queue: TensorDict | None = None
        self.trunk_steps = 0

    def next_roots(self, env: EnvBase, policy: Policy, num_roots: int) -> TensorDict:
        """Pop ``num_roots`` decision points, running new trunks when the queue is short."""
        slots = EnvSlots(env)
        while self._queue is None or self._queue.shape[0] < num_roots:
            starts = self.fresh_roots(env, slots.num_slots)
            new, steps = _trunk_roots(
                slots,
                policy if self.policy is None else self.policy,
                starts,
                self.every,
                self.max_steps,
                self.exploration_type,
            )
            new = new.exclude("trunk")
            self.trunk_steps += steps
            self._queue = new if self._queue is None else torch.cat([self._queue, new])
        out, self._queue = self._queue[:num_roots], self._queue[num_roots:]
        return out


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

    def state_dict(self) -> dict:
        """The read position."""
        return {"pos": self._pos}

    def load_state_dict(self, state_dict: dict) -> None:
        """Restore the read position."""
        self._pos = int(state_dict["pos"])
