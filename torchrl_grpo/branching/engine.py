"""The branch engine: N branches from given states, W env slots, each for up to H steps.

Scheduling: each free slot takes the next pending branch (restore its start state,
then step it). A slot whose branch ends (``done``, or H steps taken) stops being
stepped and takes the next branch at the following iteration, so with N > W the
branches run in waves without waiting for the slowest branch of a wave. The
policy runs once per iteration on the batched ``[W]`` tensordict.

Nothing here resets an env to a new episode: a slot's steps after its branch's end
never happen, so no auto-reset data can leak into a branch.

The parent process shares the cores with the workers, and every millisecond it
spends per step is taken from them. So the per-step bookkeeping works leaf by leaf
on tensors: each step's rows are written by index into preallocated ``[N * H]``
leaves (no per-step tensordict clone, exclude, stack or cat), and states are only
copied when they are kept.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching.action_checks import check_policy_actions
from torchrl_grpo.branching.keys import (
    BRANCH,
    GROUP_ID,
    ROOT_STEP,
    STATE,
    STEP_COUNT,
)
from torchrl_grpo.branching.slots import EnvSlots

KeepStates = Literal["none", "final", "all"]
Policy = Callable[[TensorDictBase], TensorDictBase | None]


@dataclass
class BranchRun:
    """What :func:`run_branches` returns.

    Attributes:
        data: ``[N, H]`` per-step data, zeros on the steps after a branch ended.
        mask: ``[N, H]`` bool, ``True`` on the steps the branch took.
        lengths: ``[N]`` int64, the number of steps each branch took.
        ended: ``[N]`` bool, the env reported ``done`` on the branch's last step.
        final_states: ``[N]`` states after each branch's last step (``keep != "none"``).
    """

    data: TensorDict
    mask: torch.Tensor
    lengths: torch.Tensor
    ended: torch.Tensor
    final_states: TensorDictBase | None


class StepRows:
    """Preallocated ``[size, ...]`` leaves, filled by index from ``[W, ...]`` tensordicts.

    The first tensordict written fixes the keys, shapes and dtypes (its leaves minus
    ``skip``); rows never written stay zero.
    """

    def __init__(self, size: int, skip: Iterable[NestedKey] = ()) -> None:
        self.size = size
        self.skip = {k if isinstance(k, tuple) else (k,) for k in skip}
        self.keys: list[NestedKey] = []
        self.leaves: list[torch.Tensor] = []
        self.views: list[np.ndarray] = []

    def _allocate(self, td: TensorDictBase) -> None:
        for key, value in td.items(True, True):
            path = key if isinstance(key, tuple) else (key,)
            if any(path[: len(s)] == s for s in self.skip):
                continue
            self.keys.append(key)
            self.leaves.append(value.new_zeros((self.size, *value.shape[1:])))

    def write(self, where: torch.Tensor, td: TensorDictBase, rows: torch.Tensor | None) -> None:
        """``self[where[i]] = td[rows[i]]`` for every leaf (``rows=None``: all rows of ``td``)."""
        if not self.keys:
            self._allocate(td)
        for key, leaf in zip(self.keys, self.leaves, strict=True):
            value = td.get(key)
            leaf.index_copy_(0, where, value if rows is None else value[rows])

    def write_rows(self, where: Sequence[int], rows: Sequence[Mapping[tuple, np.ndarray]]) -> None:
        """``self[where[i]] = rows[i]``: rows as workers send them (numpy arrays by tuple key).

        The first call fixes the keys (those of ``rows[0]`` minus ``skip``), shapes and
        dtypes; the rows are written through numpy views of the leaves, without
        building a tensordict.
        """
        if not self.keys:
            self._allocate_arrays({k: v.shape for k, v in rows[0].items()}, rows[0])
        if not self.views:
            self.views = [leaf.numpy() for leaf in self.leaves]
        for key, view in zip(self.keys, self.views, strict=True):
            for i, row in zip(where, rows, strict=True):
                view[i] = row[key]

    def write_block(self, start: int, block: Mapping[tuple, np.ndarray]) -> None:
        """``self[start : start + T] = block``: ``[T, ...]`` numpy arrays by tuple key.

        The first call fixes the keys (those of ``block`` minus ``skip``), shapes and dtypes.

        Example:
            >>> rows = StepRows(6)
            >>> rows.write_block(3, {("a",): np.ones((2, 4), np.float32)})
            >>> rows.tensordict(2, 3)["a"].sum(-1).tolist()
            [[0.0, 0.0, 0.0], [4.0, 4.0, 0.0]]
        """
        if not self.keys:
            self._allocate_arrays({k: v.shape[1:] for k, v in block.items()}, block)
        if not self.views:
            self.views = [leaf.numpy() for leaf in self.leaves]
        for key, view in zip(self.keys, self.views, strict=True):
            value = block[key]
            view[start : start + len(value)] = value

    def _allocate_arrays(
        self, shapes: Mapping[tuple, tuple], like: Mapping[tuple, np.ndarray]
    ) -> None:
        for key, shape in shapes.items():
            if any(key[: len(s)] == s for s in self.skip):
                continue
            self.keys.append(key)
            self.leaves.append(torch.from_numpy(np.zeros((self.size, *shape), like[key].dtype)))

    def tensordict(self, *shape: int) -> TensorDict:
        """The leaves as a tensordict of batch size ``shape`` (``prod(shape) == size``)."""
        out = TensorDict(batch_size=shape)
        for key, leaf in zip(self.keys, self.leaves, strict=True):
            out.set(key, leaf.view(*shape, *leaf.shape[1:]))
        return out


class RolloutRows:
    """What a rollout of N branches of at most H steps fills in, and its :class:`BranchRun`.

    The ``[N * H]`` rows of the policy's input and output (``root_rows``, minus what a
    step adds) and of each step's ``"next"`` (``next_rows``), with ``keep="all"`` the
    states before and after each step (``state_rows``); the ``[N * H]`` mask of the
    steps taken, each branch's length and whether it ended, and with ``keep != "none"``
    each branch's final state (its start state until it is written). Every engine
    (lock-step, pipelined, whole branches) writes these and returns :meth:`result`.

    Args:
        states: ``[N]`` start states of the branches.
        horizon: H.
        keep: which states the rollout keeps.
    """

    def __init__(self, states: TensorDictBase, horizon: int, keep: KeepStates) -> None:
        self.n_branches, self.horizon = states.shape[0], horizon
        size = self.n_branches * horizon
        self.lengths = torch.zeros(self.n_branches, dtype=torch.long)
        self.ended = torch.zeros(self.n_branches, dtype=torch.bool)
        self.mask = torch.zeros(size, dtype=torch.bool)
        self.final = states.clone() if keep != "none" else None
        self.root_rows = StepRows(size, skip=(STATE, "next", "_step"))
        self.next_rows = StepRows(size, skip=(STATE,))
        self.state_rows = (StepRows(size), StepRows(size)) if keep == "all" else None

    def final_state_views(self, keys: Iterable[NestedKey]) -> list[tuple[NestedKey, np.ndarray]]:
        """Numpy views of the final states' leaves ``keys`` (none when no state is kept)."""
        if self.final is None:
            return []
        return [(key, self.final.get(key).numpy()) for key in keys]

    def result(self) -> BranchRun:
        """The rollout's :class:`BranchRun`: the rows as ``[N, H]`` leaves."""
        n, h = self.n_branches, self.horizon
        data = self.root_rows.tensordict(n, h)
        data.set("next", self.next_rows.tensordict(n, h))
        if self.state_rows is not None:
            data.set(STATE, self.state_rows[0].tensordict(n, h))
            data.set(("next", STATE), self.state_rows[1].tensordict(n, h))
        return BranchRun(
            data=data,
            mask=self.mask.view(n, h),
            lengths=self.lengths,
            ended=self.ended,
            final_states=self.final,
        )


def run_branches(
    slots: EnvSlots,
    policy: Policy,
    states: TensorDictBase,
    horizon: int,
    *,
    group_id: torch.Tensor,
    branch: torch.Tensor,
    root_step: torch.Tensor,
    keep: KeepStates = "none",
    exploration_type: ExplorationType = ExplorationType.RANDOM,
) -> BranchRun:
    """Run one branch per row of ``states`` (already validated) for up to ``horizon`` steps.

    ``group_id``, ``branch`` and ``root_step`` (``[N]`` int64) are written into the
    tensordict the policy reads, with ``step_count`` (``root_step + t``), so that a
    policy may depend on them (tests script actions per branch and step).
    """
    n_branches = states.shape[0]
    width = slots.num_slots
    slot_branch = torch.full((width,), -1, dtype=torch.long)
    slot_t = torch.zeros(width, dtype=torch.long)
    run = RolloutRows(states, horizon, keep)
    lengths, ended, mask, final = run.lengths, run.ended, run.mask, run.final
    root_rows, next_rows, state_rows = run.root_rows, run.next_rows, run.state_rows
    want_states = keep != "none"
    slot_state: TensorDictBase | None = None
    cur: TensorDictBase | None = None
    next_branch = 0
    with torch.no_grad(), set_exploration_type(exploration_type):
        while True:
            free = (slot_branch < 0).nonzero().squeeze(-1)
            n_new = min(len(free), n_branches - next_branch)
            if n_new > 0:
                fill = free[:n_new]
                new = torch.arange(next_branch, next_branch + n_new)
                next_branch += n_new
                rows, snaps = slots.restore(fill, states[new], want_states=keep == "all")
                if cur is None:
                    cur = rows[:1].expand(width).clone()
                cur[fill] = rows
                if snaps is not None:
                    if slot_state is None:
                        slot_state = snaps[:1].expand(width).clone()
                    slot_state[fill] = snaps
                slot_branch[fill] = new
                slot_t[fill] = 0
            active = slot_branch >= 0
            n_active = int(active.sum())
            if n_active == 0:
                break
            # With every slot active (all steps but a rollout's tail), rows need no indexing.
            rows_idx = None if n_active == width else active.nonzero().squeeze(-1)
            td = cur.clone(False)
            idx = slot_branch.clamp(min=0)
            td.set(GROUP_ID, group_id[idx])
            td.set(BRANCH, branch[idx])
            td.set(ROOT_STEP, root_step[idx])
            td.set(STEP_COUNT, (root_step[idx] + slot_t).unsqueeze(-1))
            out = policy(td)
            td = td if out is None else out
            check_actions(td, slots)
            b = slot_branch if rows_idx is None else slot_branch[rows_idx]
            t = slot_t if rows_idx is None else slot_t[rows_idx]
            where = b * horizon + t
            root_rows.write(where, td, rows_idx)
            nxt = slots.step(td, active, want_states=want_states)
            next_rows.write(where, nxt, rows_idx)
            mask[where] = True
            done = nxt.get("done")
            done = (done if rows_idx is None else done[rows_idx]).reshape(n_active)
            t = t + 1
            finished = done | (t >= horizon)
            any_finished = bool(finished.any())
            lengths[b] = t
            ended[b] = done
            next_snap = None
            if keep == "all" or (keep == "final" and any_finished):
                next_snap = slots.next_states(nxt, rows_idx)
            if state_rows is not None:
                state_rows[0].write(where, slot_state, rows_idx)
                state_rows[1].write(where, next_snap, None)
                if rows_idx is None:
                    slot_state.update_(next_snap)
                else:
                    slot_state[rows_idx] = next_snap
            if final is not None and any_finished:
                final[b[finished]] = next_snap[finished]
            _advance(cur, nxt, rows_idx)
            if rows_idx is None:
                slot_t += 1
            else:
                slot_t[rows_idx] = t
            if any_finished:
                stepped = active.nonzero().squeeze(-1) if rows_idx is None else rows_idx
                slot_branch[stepped[finished]] = -1
    return run.result()


def _advance(cur: TensorDictBase, nxt: TensorDictBase, rows: torch.Tensor | None) -> None:
    """Copy the stepped slots' new observations and done flags into ``cur``, in place."""
    for key, leaf in cur.items(True, True):
        value = nxt.get(key)
        if rows is None:
            leaf.copy_(value)
        else:
            leaf[rows] = value[rows]


def check_actions(td: TensorDictBase, slots: EnvSlots) -> None:
    """Fail in the parent, with a readable message, before a bad action reaches a worker."""
    check_policy_actions(td, slots.action_spec, slots.action_keys, per_worker=not slots.batched)
