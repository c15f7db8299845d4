"""Where groups start: roots at episode starts, along trunks, from stored trajectories.

A *roots* tensordict has batch size ``[R]`` and holds, per root, the ``"state"`` to
branch from (a :meth:`~torchrl_grpo.envs.SnapshotEnv.get_state` state) and its
``"root_step"`` (how many steps into its episode it is). Every function here
returns one; :func:`~torchrl_grpo.branching.branch_rollout` takes one. The root
sources that feed a :class:`~torchrl_grpo.branching.GroupCollector` batch after batch
are in :mod:`~torchrl_grpo.branching.roots`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.dispatch import run_on
from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.keys import MASK, ROOT_STEP, STATE, STEP_COUNT
from torchrl_grpo.branching.rollout_rows import Policy

__all__ = [
    "as_roots",
    "draw_seed",
    "make_roots",
    "reset_roots",
    "reset_states",
    "roots_from_trajectories",
    "run_trunks",
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
    return slots.read_all_states()


def draw_seed() -> int:
    """A seed from torch's global generator (reproducible under ``torch.manual_seed``).

    Example:
        >>> _ = torch.manual_seed(0)
        >>> first = draw_seed()
        >>> _ = torch.manual_seed(0)
        >>> draw_seed() == first
        True
    """
    return int(torch.randint(0, 2**31 - 1, ()))


def reset_states(env: EnvBase, num_roots: int, seed: int | None) -> tuple[TensorDict, int]:
    """``num_roots`` fresh episode starts, and the seed that continues the sequence.

    :func:`reset_roots` without the seed; a root source keeps the seed to continue its
    sequence at its next reset.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> roots, next_seed = reset_states(HighwayEnv("merge-v0"), 2, seed=0)
        >>> roots.batch_size, next_seed != 0
        (torch.Size([2]), True)
    """
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


def run_trunks(
    slots: EnvSlots,
    policy: Policy,
    starts: TensorDict,
    every: int,
    max_steps: int | None,
    exploration_type: ExplorationType,
) -> tuple[TensorDict, int]:
    """Decision points of trunks from ``starts``, and the number of trunk steps taken.

    :func:`trunk_roots` on an env's slots, with each root's ``"trunk"`` and the steps
    the trunks took.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> env = HighwayEnv("highway-fast-v0")
        >>> starts = reset_roots(env, 1, seed=0)
        >>> roots, steps = run_trunks(EnvSlots(env), ConstantActionPolicy("IDLE"), starts,
        ...                           every=2, max_steps=5,
        ...                           exploration_type=ExplorationType.RANDOM)
        >>> roots["root_step"].tolist(), steps
        ([0, 2, 4], 6)
    """
    n_trunks = starts.shape[0]
    cur = starts.clone(False).set("trunk", torch.arange(n_trunks))
    found = [cur]
    steps_taken = 0
    while cur.shape[0]:
        run = run_on(
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
    return run_trunks(slots, policy, starts, every, max_steps, exploration_type)[0]


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
