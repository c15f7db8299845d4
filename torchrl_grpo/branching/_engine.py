"""The branch engine: N branches from given states, W env slots, each for up to H steps.

Scheduling: each free slot takes the next pending branch (restore its start state,
then step it). A slot whose branch ends (``done``, or H steps taken) stops being
stepped and takes the next branch at the following iteration, so with N > W the
branches run in waves without waiting for the slowest branch of a wave. The
policy runs once per iteration on the batched ``[W]`` tensordict.

Nothing here resets an env to a new episode: a slot's steps after its branch's end
never happen, so no auto-reset data can leak into a branch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching._slots import EnvSlots
from torchrl_grpo.branching.keys import (
    BRANCH,
    GROUP_ID,
    ROOT_STEP,
    STATE,
    STEP_COUNT,
)

KeepStates = Literal["none", "final", "all"]
Policy = Callable[[TensorDictBase], TensorDictBase | None]

_STATE_KEYS = (STATE, ("next", STATE))


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
    lengths = torch.zeros(n_branches, dtype=torch.long)
    ended = torch.zeros(n_branches, dtype=torch.bool)
    final = states.clone() if keep != "none" else None
    records: list[tuple[torch.Tensor, torch.Tensor, TensorDictBase]] = []
    cur: TensorDictBase | None = None
    slot_state: TensorDictBase | None = None
    next_branch = 0
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
            if keep == "all":
                if slot_state is None:
                    slot_state = snaps[:1].expand(width).clone()
                slot_state[fill] = snaps
            slot_branch[fill] = new
            slot_t[fill] = 0
        active = slot_branch >= 0
        if not bool(active.any()):
            break
        td = cur.clone(False)
        idx = slot_branch.clamp(min=0)
        td.set(GROUP_ID, group_id[idx])
        td.set(BRANCH, branch[idx])
        td.set(ROOT_STEP, root_step[idx])
        td.set(STEP_COUNT, (root_step[idx] + slot_t).unsqueeze(-1))
        with torch.no_grad(), set_exploration_type(exploration_type):
            out = policy(td)
        td = td if out is None else out
        _check_actions(td, slots)
        td = slots.step(td, active)
        rows_idx = active.nonzero().squeeze(-1)
        b = slot_branch[rows_idx]
        t = slot_t[rows_idx]
        done = td.get(("next", "done"))[rows_idx].reshape(len(rows_idx))
        slot_t[rows_idx] += 1
        finished = done | (slot_t[rows_idx] >= horizon)
        lengths[b] = slot_t[rows_idx]
        ended[b] = done
        next_snap = None
        if keep == "all" or (keep == "final" and bool(finished.any())):
            next_snap = slots.next_states(td, rows_idx)
        rec = td.exclude(*_STATE_KEYS)[rows_idx]
        if keep == "all":
            rec.set(STATE, slot_state[rows_idx])
            rec.set(("next", STATE), next_snap)
            slot_state[rows_idx] = next_snap
        if final is not None and bool(finished.any()):
            final[b[finished]] = next_snap[finished]
        records.append((b, t, rec))
        cur[rows_idx] = td.get("next").select(*cur.keys(True, True))[rows_idx]
        slot_branch[rows_idx[finished]] = -1
    return _assemble(records, n_branches, horizon, lengths, ended, final)


def _assemble(
    records: list[tuple[torch.Tensor, torch.Tensor, TensorDictBase]],
    n_branches: int,
    horizon: int,
    lengths: torch.Tensor,
    ended: torch.Tensor,
    final: TensorDictBase | None,
) -> BranchRun:
    b = torch.cat([r[0] for r in records])
    t = torch.cat([r[1] for r in records])
    flat = torch.cat([r[2] for r in records])
    size = n_branches * horizon
    data = flat[:1].clone().zero_().expand(size).clone()
    where = b * horizon + t
    data[where] = flat
    mask = torch.zeros(size, dtype=torch.bool)
    mask[where] = True
    return BranchRun(
        data=data.reshape(n_branches, horizon),
        mask=mask.reshape(n_branches, horizon),
        lengths=lengths,
        ended=ended,
        final_states=final,
    )


def _check_actions(td: TensorDictBase, slots: EnvSlots) -> None:
    """Fail in the parent, with a readable message, before a bad action reaches a worker."""
    spec = slots.action_spec
    for key in slots.action_keys:
        leaf = spec[key]
        expected = tuple(leaf.shape) if slots.batched else (1, *leaf.shape)
        action = td.get(key, None)
        if action is None:
            raise ValueError(
                f"the policy wrote no {key!r} entry (its output has "
                f"{sorted(map(str, td.keys(True, True)))}); it must write the env's action"
            )
        if (
            not isinstance(action, torch.Tensor)
            or tuple(action.shape) != expected
            or (action.dtype != leaf.dtype)
        ):
            got = (
                (tuple(action.shape), action.dtype)
                if isinstance(action, torch.Tensor)
                else (type(action).__name__)
            )
            raise ValueError(
                f"the policy's {key!r} does not match the env's action spec: got {got}, "
                f"expected shape {expected} and dtype {leaf.dtype} ({type(leaf).__name__} "
                f"spec{_spec_range(leaf)})"
            )
        if not leaf.is_in(action if slots.batched else action[0]):
            raise ValueError(
                f"the policy's {key!r} holds values outside the env's action spec"
                f"{_spec_range(leaf)}: {action.reshape(-1).tolist()[:8]}"
            )


def _spec_range(spec) -> str:
    n = getattr(spec, "n", None)
    if n is not None:
        return f" with {n} actions, indices 0..{n - 1}"
    return ""
