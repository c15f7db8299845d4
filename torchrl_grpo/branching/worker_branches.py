"""Whole branches in the workers: each worker runs branches with its own copy of the policy.

On a :class:`~torchrl_grpo.branching.BranchParallelEnv`, the parent pickles the policy
once per rollout and sends it to every worker
(:mod:`~torchrl_grpo.branching.policy_transport`); then it hands each worker one branch
at a time (restore, then policy and step until ``done`` or H steps, in the worker:
:class:`~torchrl_grpo.branching.branch_runner.BranchRunner`). A worker answers once
per branch, and gets its next branch as soon as it answers, so no worker waits for
another's branches, and the parent does nothing per step: it sleeps until an answer
comes, sends the next branch, and copies the answer's rows into the rollout's
preallocated ``[N * H]`` leaves. On W workers and W cores, the workers then have the
cores to themselves.

Each branch's samples are seeded from the rollout's base seeds (drawn in the parent)
and the branch's index, so a rollout is reproducible and does not depend on W or on
which worker ran which branch. The policy is called on a batch of one row, as on a
plain env: a policy that acts on a branch's own inputs gives bitwise the data of the
``"single"`` backend, and, with a scripted policy, of every backend.

:func:`run_whole_branches` returns ``None`` when the policy cannot be sent (it does
not pickle, holds tensors off the CPU, or a worker cannot unpickle it): the caller
then runs the rollout with the policy in the parent
(:func:`~torchrl_grpo.branching.lockstep.run_branches`).
"""

from __future__ import annotations

import pickle
from collections import deque

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.branch_runner import RolloutSetup
from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.pipe_arrays import STATE_ALWAYS, STATE_AT_END, STATE_NEVER, to_arrays
from torchrl_grpo.branching.policy_transport import pack_policy
from torchrl_grpo.branching.rollout_rows import BranchRun, KeepStates, Policy, RolloutRows

__all__ = ["run_whole_branches"]


def run_whole_branches(
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
) -> BranchRun | None:
    """Run one branch per row of ``states`` in ``slots``' workers; ``None`` if the policy can't go.

    ``slots.env`` is a :class:`~torchrl_grpo.branching.BranchParallelEnv` whose
    :meth:`~torchrl_grpo.branching.BranchParallelEnv.whole_branches_apply` is true; the
    other arguments and the result are :func:`~torchrl_grpo.branching.lockstep.run_branches`'.

    Example:
        >>> import functools
        >>> from torchrl_grpo.branching import reset_roots, shutdown_env
        >>> from torchrl_grpo.branching.workers import BranchParallelEnv
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> make = functools.partial(HighwayEnv, "merge-v0", return_state=True)
        >>> env = BranchParallelEnv(2, make, mp_start_method="fork")
        >>> roots = reset_roots(make(), 1, seed=0).get("state").expand(3)
        >>> ids = torch.zeros(3, dtype=torch.int64)
        >>> run = run_whole_branches(EnvSlots(env), RandomPolicy(seed=0), roots, 2,
        ...                          group_id=ids, branch=ids, root_step=ids)
        >>> run.lengths.tolist(), run.data.batch_size
        ([2, 2, 2], torch.Size([3, 2]))
        >>> run_whole_branches(EnvSlots(env), lambda td: td, roots, 2, group_id=ids,
        ...                    branch=ids, root_step=ids) is None  # a lambda stays here
        True
        >>> shutdown_env(env)
    """
    packed = pack_policy(policy)
    if packed is None:
        return None
    mode = {"none": STATE_NEVER, "final": STATE_AT_END, "all": STATE_ALWAYS}[keep]
    keys = [*slots.obs_keys, *slots.done_keys]
    setup = RolloutSetup(packed, keys, slots.next_keys, mode, horizon, exploration_type)
    run = _Dispatch(slots, states, horizon, keep, (group_id, branch, root_step))
    try:
        if not run.start(setup):
            return None
        run.run()
    except BaseException:
        run.drain()
        raise
    return run.result()


class _Dispatch(RolloutRows):
    """The bookkeeping of one rollout: branches in flight per worker, rows, results."""

    def __init__(
        self,
        slots: EnvSlots,
        states: TensorDictBase,
        horizon: int,
        keep: KeepStates,
        ids: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    ) -> None:
        super().__init__(states, horizon, keep)
        self.env, self.width = slots.env, slots.num_slots
        self.depth = max(1, int(self.env.branch_queue_depth))
        self.ids = [t.tolist() for t in ids]
        # Each branch job sends one row of these: a numpy index per leaf.
        self.state_arrays = to_arrays(states)
        self.in_flight: list[deque[int]] = [deque() for _ in range(self.width)]
        self.next_branch = 0
        self.final_views = self.final_state_views(self.state_arrays)
        self.setup_due = [False] * self.width

    # ------------------------------------------------------------------ messages
    def start(self, setup: RolloutSetup) -> bool:
        """Send every worker the rollout's setup; whether all of them can run it."""
        for w in range(self.width):
            self.env.branch_run_send(w, ("setup", setup))
            self.setup_due[w] = True
        usable = True
        for w in range(self.width):
            self.setup_due[w] = False
            answer = self.env.branch_answer(w)
            if answer[0] == "error":
                self.raise_error(w, answer)
            usable = usable and answer[0] == "ready"
        return usable

    def send_next(self, worker: int) -> None:
        """Hand ``worker`` the next pending branch."""
        b = self.next_branch
        state = {k: v[b, ...] for k, v in self.state_arrays.items()}
        labels = (self.ids[0][b], self.ids[1][b], self.ids[2][b])
        self.env.branch_run_send(worker, ("branch", b, state, labels))
        self.in_flight[worker].append(b)
        self.next_branch += 1

    def wants_more(self, worker: int) -> bool:
        """Whether ``worker`` takes another branch now.

        Up to :attr:`depth` queued branches while at least one branch per worker is
        pending; then one at a time, so that the last branches go to whichever
        worker frees up first and the workers finish together.
        """
        pending = self.n_branches - self.next_branch
        if pending == 0:
            return False
        limit = self.depth if pending >= self.width else 1
        return len(self.in_flight[worker]) < limit

    def drain(self) -> None:
        """Read every answer still due, so that the next rollout starts with empty pipes."""
        for w in range(self.width):
            due = len(self.in_flight[w]) + int(self.setup_due[w])
            for _ in range(due):
                try:
                    self.env.branch_answer(w)
                except Exception:  # noqa: BLE001 - the first error is the one raised
                    break
            self.in_flight[w].clear()
            self.setup_due[w] = False

    def raise_error(self, worker: int, answer: tuple) -> None:
        """Raise the exception of ``worker``'s error ``answer`` (after draining the others)."""
        _, blob, trace = answer
        self.drain()
        err = None
        if blob is not None:
            try:
                err = pickle.loads(blob)
            except Exception:  # noqa: BLE001 - raised as a RuntimeError below
                err = None
        where = RuntimeError(f"branch worker {worker} failed:\n{trace}")
        if isinstance(err, BaseException):
            raise err from where
        raise where

    # ------------------------------------------------------------------ schedule
    def run(self) -> None:
        for w in range(self.width):
            while self.wants_more(w):
                self.send_next(w)
        busy = [w for w in range(self.width) if self.in_flight[w]]
        while busy:
            for w in self.env.branch_ready(busy):
                answer = self.env.branch_answer(w)
                self.in_flight[w].popleft()
                if answer[0] != "branch":
                    self.raise_error(w, answer)
                # The worker's next branch first: it steps while the rows are copied.
                while self.wants_more(w):
                    self.send_next(w)
                self.take(answer[1])
            busy = [w for w in range(self.width) if self.in_flight[w]]

    def take(self, rows: dict) -> None:
        """Copy one branch's answer into the rollout's leaves."""
        b, length = rows["index"], rows["length"]
        start = b * self.horizon
        self.root_rows.write_block(start, rows["root"])
        self.next_rows.write_block(start, rows["next"])
        if self.state_rows is not None:
            self.state_rows[0].write_block(start, rows["before"])
            self.state_rows[1].write_block(start, rows["after"])
        self.mask[start : start + length] = True
        self.lengths[b], self.ended[b] = length, rows["ended"]
        if self.final is not None:
            for key, view in self.final_views:
                view[b] = rows["final"][key]
