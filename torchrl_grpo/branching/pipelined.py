"""Pipelined branch rollouts on a :class:`~torchrl_grpo.branching.BranchParallelEnv`.

Each of the W workers holds L lanes (envs); lane ``j`` of every worker makes a row of
lane ``j``'s ``[W]`` batch. The parent visits the lanes in turn. For lane ``j`` it
reads the workers' answers to the jobs it sent for that lane, runs the policy once on
the lane's ``[W]`` rows and sends the next jobs, then moves on to lane ``j + 1``. A
worker's jobs queue in its pipe, so it steps lane ``j + 1`` while the parent works on
lane ``j``, and it has no wait for a slow branch of another worker until its queue
runs dry. With one lane this is the lock-step engine, with a pipe round trip instead
of a shared-buffer one.

The schedule depends on the branches' lengths only, never on timing, so a sampling
policy draws the same samples in every run. Each branch's steps are its own
state's and actions': results match the serial backend bit for bit for policies that
choose a branch's actions from its own inputs (scripted ones, or deterministic ones).

A slot whose branch ends takes the next branch with a restore job; the restored
observations come back with the lane's next answers. In the last wave, a worker that
has more steps queued than the others leaves the next branch to them
(:func:`leave_to_others`), so that the workers finish together. No slot is stepped past its
branch's end, so no auto-reset data reaches a branch.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching.engine import (
    BranchRun,
    KeepStates,
    Policy,
    RolloutRows,
    check_actions,
)
from torchrl_grpo.branching.keys import BRANCH, GROUP_ID, ROOT_STEP, STEP_COUNT
from torchrl_grpo.branching.lanes import (
    STATE_ALWAYS,
    STATE_AT_END,
    STATE_NEVER,
    Arrays,
    from_arrays,
    to_arrays,
)
from torchrl_grpo.branching.slots import EnvSlots

__all__ = ["leave_to_others", "run_pipelined"]

# A slot's branch: none, being restored (its answer is pending), or being stepped.
_FREE, _RESTORING, _STEPPING = 0, 1, 2


def run_pipelined(
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
    """Run one branch per row of ``states`` on ``slots``' lanes; what :func:`run_branches` does.

    ``slots.env`` is a :class:`~torchrl_grpo.branching.BranchParallelEnv` whose
    :meth:`~torchrl_grpo.branching.BranchParallelEnv.branch_lanes_apply` is true; the
    other arguments and the result are :func:`~torchrl_grpo.branching.engine.run_branches`'.

    Example:
        >>> import functools
        >>> from torchrl_grpo.branching import reset_roots, shutdown_env
        >>> from torchrl_grpo.branching.workers import BranchParallelEnv
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> make = functools.partial(HighwayEnv, "merge-v0", return_state=True)
        >>> env = BranchParallelEnv(1, make, mp_start_method="fork")
        >>> roots = reset_roots(make(), 1, seed=0).get("state").expand(3)
        >>> zero = torch.zeros(3, dtype=torch.int64)
        >>> idle = lambda td: td.set("action", torch.ones(1, dtype=torch.int64))
        >>> run = run_pipelined(EnvSlots(env), idle, roots, 2, group_id=zero, branch=zero,
        ...                     root_step=zero)
        >>> run.lengths.tolist(), run.data.batch_size
        ([2, 2, 2], torch.Size([3, 2]))
        >>> shutdown_env(env)
    """
    run = _Pipeline(slots, states, horizon, keep, (group_id, branch, root_step))
    with torch.no_grad(), set_exploration_type(exploration_type):
        try:
            run.run(policy)
        except BaseException:
            run.drain()
            raise
    return run.result()


def leave_to_others(queued: list[int], worker: int, horizon: int) -> bool:
    """In a rollout's last wave, whether ``worker`` leaves the next branch to another.

    ``queued[w]`` is the most steps worker ``w``'s branches may still take. The rollout
    ends when its last worker does, and a worker with nothing left idles until then;
    so a worker that has half a branch (``horizon / 2`` steps) more queued than the
    least loaded one takes no new branch. It depends on the schedule only, never on
    timing, so runs stay reproducible.

    Example:
        >>> leave_to_others([12, 1], 0, 8), leave_to_others([12, 1], 1, 8)
        (True, False)
        >>> leave_to_others([5, 1], 0, 8), leave_to_others([0, 0], 0, 8)
        (False, False)
    """
    return queued[worker] > 0 and 2 * queued[worker] > 2 * min(queued) + horizon


class _Pipeline(RolloutRows):
    """The bookkeeping of one pipelined rollout: slots ``[L, W]``, rows, pending answers.

    The parent's every millisecond per step is taken from the workers (W workers on
    W cores), so the bookkeeping works on the workers' numpy answers directly: slot
    state in Python lists, answers written into preallocated leaves through numpy
    views (:meth:`StepRows.write_rows`), one tensordict per lane (its rows updated in
    place) for the policy to read.
    """

    def __init__(
        self,
        slots: EnvSlots,
        states: TensorDictBase,
        horizon: int,
        keep: KeepStates,
        ids: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    ) -> None:
        super().__init__(states, horizon, keep)
        self.slots, self.env, self.keep = slots, slots.env, keep
        self.ids = ids
        self.width = slots.num_slots
        self.lanes = self.env.branch_lanes
        self.keys = ([*slots.obs_keys, *slots.done_keys], slots.next_keys)
        # Each restore sends one row of these: a numpy index per leaf, no tensordict.
        self.state_arrays = to_arrays(states)
        self.slot_branch = [[-1] * self.width for _ in range(self.lanes)]
        self.slot_t = [[0] * self.width for _ in range(self.lanes)]
        self.phase = [[_FREE] * self.width for _ in range(self.lanes)]
        self.pending = [0] * self.width
        self.final_views = self.final_state_views(self.state_arrays)
        self.step_mode = {"none": STATE_NEVER, "final": STATE_AT_END, "all": STATE_ALWAYS}[keep]
        # Each lane's [W] rows for the policy, and numpy views of their leaves.
        self.cur: list[TensorDictBase | None] = [None] * self.lanes
        self.cur_views: list[list[tuple[tuple, np.ndarray]]] = [[] for _ in range(self.lanes)]
        # keep="all": each slot's state before its next step.
        self.before: list[list[Arrays | None]] = [[None] * self.width for _ in range(self.lanes)]
        self.next_branch = 0

    # ------------------------------------------------------------------ messages
    def send(self, worker: int, job: tuple) -> None:
        self.env.branch_send(worker, [job], *self.keys)
        self.pending[worker] += 1

    def receive(self, worker: int) -> dict:
        self.pending[worker] -= 1
        return self.env.branch_receive(worker)[0]

    def drain(self) -> None:
        """Read every answer still due, so that the next rollout starts with empty pipes."""
        for worker, count in enumerate(self.pending):
            for _ in range(count):
                try:
                    self.receive(worker)
                except Exception:  # noqa: BLE001 - the first error is the one raised
                    pass

    # ------------------------------------------------------------------ schedule
    def run(self, policy: Policy) -> None:
        for lane in range(self.lanes):
            self.restore_free(lane)
        lane = 0
        while any(p != _FREE for phases in self.phase for p in phases):
            phase = self.phase[lane]
            busy = [w for w in range(self.width) if phase[w] != _FREE]
            answers = {w: self.receive(w) for w in busy}
            restored = [w for w in busy if phase[w] == _RESTORING]
            stepped = [w for w in busy if phase[w] == _STEPPING]
            if restored:
                self.take_restores(lane, restored, answers)
            if stepped:
                self.take_steps(lane, stepped, answers)
            self.restore_free(lane)
            ready = [w for w in range(self.width) if phase[w] == _STEPPING]
            if ready:
                self.step_lane(policy, lane, ready)
            lane = (lane + 1) % self.lanes

    def restore_free(self, lane: int) -> None:
        """Send the next pending branches to the free slots of ``lane``."""
        for w in range(self.width):
            if self.phase[lane][w] != _FREE:
                continue
            if self.next_branch >= self.n_branches:
                return
            if self.holds_back(w):
                continue
            b = self.next_branch
            state = {k: v[b, ...] for k, v in self.state_arrays.items()}
            self.send(w, ("restore", lane, state, self.keep == "all"))
            self.slot_branch[lane][w], self.slot_t[lane][w] = b, 0
            self.phase[lane][w] = _RESTORING
            self.next_branch += 1

    def holds_back(self, worker: int) -> bool:
        """Whether ``worker``'s free slot stays empty for now (see :func:`leave_to_others`)."""
        if self.n_branches - self.next_branch >= self.width * self.lanes:
            return False  # not the last wave yet: every free slot takes a branch
        queued = [self.queued_steps(w) for w in range(self.width)]
        return leave_to_others(queued, worker, self.horizon)

    def queued_steps(self, worker: int) -> int:
        """The most steps ``worker``'s branches may still take (``horizon - t`` each)."""
        return sum(
            self.horizon - self.slot_t[lane][worker]
            for lane in range(self.lanes)
            if self.phase[lane][worker] != _FREE
        )

    def set_rows(self, lane: int, rows: dict[int, Arrays]) -> None:
        """Write the workers' ``rows`` (answers' ``"out"``) into ``lane``'s policy rows."""
        if self.cur[lane] is None:
            # Rows no branch has reached yet hold a copy of the first row.
            self.cur[lane] = from_arrays([next(iter(rows.values()))] * self.width)
            self.cur_views[lane] = [
                (key, self.cur[lane].get(key).numpy()) for key in next(iter(rows.values()))
            ]
        for key, view in self.cur_views[lane]:
            for w, row in rows.items():
                view[w] = row[key]

    def take_restores(self, lane: int, restored: list[int], answers: dict) -> None:
        self.set_rows(lane, {w: answers[w]["out"] for w in restored})
        for w in restored:
            if self.state_rows is not None:
                self.before[lane][w] = answers[w]["state"]
            self.phase[lane][w] = _STEPPING

    def take_steps(self, lane: int, stepped: list[int], answers: dict) -> None:
        horizon, slot_b, slot_t = self.horizon, self.slot_branch[lane], self.slot_t[lane]
        where = [slot_b[w] * horizon + slot_t[w] for w in stepped]
        rows = [answers[w]["out"] for w in stepped]
        self.next_rows.write_rows(where, rows)
        if self.state_rows is not None:
            snaps = [answers[w]["state"] for w in stepped]
            self.state_rows[0].write_rows(where, [self.before[lane][w] for w in stepped])
            self.state_rows[1].write_rows(where, snaps)
            for w, snap in zip(stepped, snaps, strict=True):
                self.before[lane][w] = snap
        self.set_rows(lane, dict(zip(stepped, rows, strict=True)))
        for w, row in zip(stepped, rows, strict=True):
            b, t, done = slot_b[w], slot_t[w] + 1, bool(row[("done",)].any())
            self.lengths[b], self.ended[b] = t, done
            slot_t[w] = t
            if done or t >= horizon:
                if self.final is not None:
                    for key, view in self.final_views:
                        view[b] = answers[w]["state"][key]
                self.phase[lane][w] = _FREE
                slot_b[w] = -1

    def step_lane(self, policy: Policy, lane: int, ready: list[int]) -> None:
        """Run the policy on ``lane``'s ``[W]`` rows; send the ``ready`` slots their steps."""
        group_id, branch, root_step = self.ids
        slot_b, slot_t = self.slot_branch[lane], self.slot_t[lane]
        td = self.cur[lane].clone(False)
        idx = torch.tensor([max(b, 0) for b in slot_b])
        td.set(GROUP_ID, group_id[idx])
        td.set(BRANCH, branch[idx])
        td.set(ROOT_STEP, root_step[idx])
        td.set(STEP_COUNT, (root_step[idx] + torch.tensor(slot_t)).unsqueeze(-1))
        out = policy(td)
        td = td if out is None else out
        check_actions(td, self.slots)
        where = [slot_b[w] * self.horizon + slot_t[w] for w in ready]
        self.root_rows.write(
            torch.tensor(where), td, None if len(ready) == self.width else torch.tensor(ready)
        )
        self.mask[where] = True
        actions = [(_as_tuple(k), td.get(k).numpy()) for k in self.slots.action_keys]
        for w in ready:
            last = slot_t[w] + 1 >= self.horizon
            action = {key: value[w, ...] for key, value in actions}
            self.send(w, ("step", lane, action, self.step_mode, last))


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return key if isinstance(key, tuple) else (key,)
