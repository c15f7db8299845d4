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
observations come back with the lane's next answers. No slot is stepped past its
branch's end, so no auto-reset data reaches a branch.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching.engine import BranchRun, KeepStates, Policy, StepRows, check_actions
from torchrl_grpo.branching.keys import BRANCH, GROUP_ID, ROOT_STEP, STATE, STEP_COUNT
from torchrl_grpo.branching.lanes import (
    STATE_ALWAYS,
    STATE_AT_END,
    STATE_NEVER,
    from_arrays,
    to_arrays,
)
from torchrl_grpo.branching.slots import EnvSlots

__all__ = ["run_pipelined"]

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
        >>> from torchrl_grpo.branching import BranchParallelEnv, reset_roots, shutdown_env
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


class _Pipeline:
    """The bookkeeping of one pipelined rollout: slots ``[L, W]``, rows, pending answers."""

    def __init__(
        self,
        slots: EnvSlots,
        states: TensorDictBase,
        horizon: int,
        keep: KeepStates,
        ids: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    ) -> None:
        self.slots, self.env, self.states, self.horizon, self.keep = (
            slots,
            slots.env,
            states,
            horizon,
            keep,
        )
        self.ids = ids
        self.n_branches, self.width, self.lanes = (
            states.shape[0],
            slots.num_slots,
            self.env.branch_lanes,
        )
        size = self.n_branches * horizon
        self.keys = ([*slots.obs_keys, *slots.done_keys], slots.next_keys)
        shape = (self.lanes, self.width)
        self.slot_branch = torch.full(shape, -1, dtype=torch.long)
        self.slot_t = torch.zeros(shape, dtype=torch.long)
        self.phase = torch.full(shape, _FREE, dtype=torch.long)
        self.pending = [0] * self.width
        self.lengths = torch.zeros(self.n_branches, dtype=torch.long)
        self.ended = torch.zeros(self.n_branches, dtype=torch.bool)
        self.mask = torch.zeros(size, dtype=torch.bool)
        self.final = states.clone() if keep != "none" else None
        self.root_rows = StepRows(size, skip=(STATE, "next", "_step"))
        self.next_rows = StepRows(size, skip=(STATE,))
        self.state_rows = (StepRows(size), StepRows(size)) if keep == "all" else None
        self.step_mode = {"none": STATE_NEVER, "final": STATE_AT_END, "all": STATE_ALWAYS}[keep]
        self.cur: list[TensorDictBase | None] = [None] * self.lanes  # each lane's [W] rows
        self.before: list[TensorDictBase | None] = [None] * self.lanes  # states before a step
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
        while bool((self.phase != _FREE).any()):
            busy = (self.phase[lane] != _FREE).nonzero().squeeze(-1).tolist()
            answers = {w: self.receive(w) for w in busy}
            restored = [w for w in busy if self.phase[lane, w] == _RESTORING]
            stepped = [w for w in busy if self.phase[lane, w] == _STEPPING]
            if restored:
                self.take_restores(lane, restored, answers)
            if stepped:
                self.take_steps(lane, stepped, answers)
            self.restore_free(lane)
            ready = (self.phase[lane] == _STEPPING).nonzero().squeeze(-1)
            if len(ready):
                self.step_lane(policy, lane, ready)
            lane = (lane + 1) % self.lanes

    def restore_free(self, lane: int) -> None:
        """Send the next pending branches to the free slots of ``lane``."""
        for w in (self.phase[lane] == _FREE).nonzero().squeeze(-1).tolist():
            if self.next_branch >= self.n_branches:
                return
            b = self.next_branch
            self.send(w, ("restore", lane, to_arrays(self.states[b]), self.keep == "all"))
            self.slot_branch[lane, w], self.slot_t[lane, w] = b, 0
            self.phase[lane, w] = _RESTORING
            self.next_branch += 1

    def take_restores(self, lane: int, restored: list[int], answers: dict) -> None:
        rows = torch.tensor(restored)
        out = from_arrays([answers[w]["out"] for w in restored])
        if self.cur[lane] is None:
            self.cur[lane] = out[:1].expand(self.width).clone()
        self.cur[lane][rows] = out
        if self.state_rows is not None:
            snaps = from_arrays([answers[w]["state"] for w in restored])
            if self.before[lane] is None:
                self.before[lane] = snaps[:1].expand(self.width).clone()
            self.before[lane][rows] = snaps
        self.phase[lane, rows] = _STEPPING

    def take_steps(self, lane: int, stepped: list[int], answers: dict) -> None:
        rows = torch.tensor(stepped)
        b, t = self.slot_branch[lane, rows], self.slot_t[lane, rows]
        where = b * self.horizon + t
        nxt = from_arrays([answers[w]["out"] for w in stepped])
        self.next_rows.write(where, nxt, None)
        done = nxt.get("done").reshape(len(stepped))
        t = t + 1
        finished = done | (t >= self.horizon)
        self.lengths[b], self.ended[b] = t, done
        if self.state_rows is not None:
            snaps = from_arrays([answers[w]["state"] for w in stepped])
            self.state_rows[0].write(where, self.before[lane][rows], None)
            self.state_rows[1].write(where, snaps, None)
            self.before[lane][rows] = snaps
        if self.final is not None and bool(finished.any()):
            ends = finished.nonzero().squeeze(-1).tolist()
            self.final[b[ends]] = from_arrays([answers[stepped[i]]["state"] for i in ends])
        for key, leaf in self.cur[lane].items(True, True):
            leaf[rows] = nxt.get(key)
        self.slot_t[lane, rows] = t
        self.phase[lane, rows[finished]] = _FREE
        self.slot_branch[lane, rows[finished]] = -1

    def step_lane(self, policy: Policy, lane: int, ready: torch.Tensor) -> None:
        """Run the policy on ``lane``'s ``[W]`` rows; send the ``ready`` slots their steps."""
        group_id, branch, root_step = self.ids
        slot_branch, slot_t = self.slot_branch[lane], self.slot_t[lane]
        td = self.cur[lane].clone(False)
        idx = slot_branch.clamp(min=0)
        td.set(GROUP_ID, group_id[idx])
        td.set(BRANCH, branch[idx])
        td.set(ROOT_STEP, root_step[idx])
        td.set(STEP_COUNT, (root_step[idx] + slot_t).unsqueeze(-1))
        out = policy(td)
        td = td if out is None else out
        check_actions(td, self.slots)
        b, t = slot_branch[ready], slot_t[ready]
        where = b * self.horizon + t
        self.root_rows.write(where, td, ready)
        self.mask[where] = True
        actions = td.select(*self.slots.action_keys)
        last = (t + 1 >= self.horizon).tolist()
        for i, w in enumerate(ready.tolist()):
            self.send(w, ("step", lane, to_arrays(actions[w]), self.step_mode, last[i]))

    def result(self) -> BranchRun:
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
