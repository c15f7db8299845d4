"""The lock-step engine: the policy in this process, W env slots stepped together.

It runs the branches of a snapshot env whose policy runs in this process: a plain env
(one slot), a ``SerialEnv`` or TorchRL ``ParallelEnv`` of W workers, and a
:class:`~torchrl_grpo.branching.BranchParallelEnv` whose policy cannot be sent to its
workers (see :mod:`~torchrl_grpo.branching.worker_branches`, the engine that runs
otherwise on those workers).

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

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching.action_checks import check_policy_actions
from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.keys import BRANCH, GROUP_ID, ROOT_STEP, STEP_COUNT
from torchrl_grpo.branching.rollout_rows import BranchRun, KeepStates, Policy, RolloutRows

__all__ = ["check_actions", "run_branches"]


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
