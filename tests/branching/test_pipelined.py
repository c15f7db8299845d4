"""Pipelined branch rollouts: BranchParallelEnv lanes against the lock-step engine."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from branching_helpers import (
    SHORT,
    ScheduledPolicy,
    bitwise_equal,
    branch_env,
    mixed_actions,
    mlp_actor,
    plain_env,
)
from tensordict import TensorDict

from torchrl_grpo.branching import branch_rollout, make_branch_env, reset_roots, shutdown_env
from torchrl_grpo.branching.batched import run_on
from torchrl_grpo.branching.pipelined import leave_to_others
from torchrl_grpo.branching.slots import EnvSlots
from torchrl_grpo.envs import states_equal

SCENARIO = "highway-fast-v0"
CONFIG = SHORT[SCENARIO]


def _table():
    return mixed_actions(SCENARIO)


@pytest.fixture(scope="module")
def short_parallel():
    env = make_branch_env(SCENARIO, 2, config=CONFIG, mp_start_method="fork")
    # These tests are about the lanes: whole branches in the workers are off.
    env.whole_branches = False
    yield env
    shutdown_env(env)


@pytest.fixture(scope="module")
def roots():
    return reset_roots(plain_env(SCENARIO, config=CONFIG), 2, seed=0)


def test_parallel_envs_run_pipelined_unless_told_otherwise(short_parallel):
    assert EnvSlots(short_parallel).pipelined
    short_parallel.branch_lanes = 0
    try:
        assert not EnvSlots(short_parallel).pipelined
    finally:
        del short_parallel.branch_lanes
    serial = branch_env(SCENARIO, "serial")
    assert not EnvSlots(serial).pipelined
    shutdown_env(serial)


@pytest.mark.parametrize("return_states", [False, True])
def test_any_number_of_lanes_gives_the_serial_backend_data(short_parallel, roots, return_states):
    # 10 branches of up to 6 steps on 2 workers; short episodes end some branches early,
    # so slots take new branches mid-rollout and lanes fall out of step.
    serial = make_branch_env(SCENARIO, 2, config=CONFIG, backend="serial")
    try:
        reference = branch_rollout(
            serial, ScheduledPolicy(_table()), roots, 5, 6, return_states=return_states
        )
    finally:
        shutdown_env(serial)
    assert not reference["mask"].all()
    for lanes in (1, 2, 3, 0):
        short_parallel.branch_lanes = lanes
        try:
            data = branch_rollout(
                short_parallel, ScheduledPolicy(_table()), roots, 5, 6, return_states=return_states
            )
        finally:
            del short_parallel.branch_lanes
        assert bitwise_equal(reference, data) == [], lanes


def test_final_states_are_those_of_the_lock_step_engine(short_parallel, roots):
    states = roots["state"][torch.tensor([0, 0, 1, 1, 1])]
    ids = {name: torch.arange(5) for name in ("group_id", "branch", "root_step")}
    ids["root_step"] = torch.zeros(5, dtype=torch.long)
    runs = {}
    for lanes in (2, 0):
        short_parallel.branch_lanes = lanes
        try:
            slots = EnvSlots(short_parallel)
            runs[lanes] = run_on(slots, ScheduledPolicy(_table()), states, 6, keep="final", **ids)
        finally:
            del short_parallel.branch_lanes
    assert torch.equal(runs[2].lengths, runs[0].lengths)
    assert runs[2].ended.any()
    for i in range(5):
        assert states_equal(runs[2].final_states[i], runs[0].final_states[i]), i
    # Each final state is the branch's: stepping its root with its actions gets there.
    check = plain_env(SCENARIO, config=CONFIG)
    check.set_state(states[3])
    for t in range(int(runs[2].lengths[3])):
        check.step(TensorDict(action=_table()[3, t]))
    assert states_equal(check.get_state(), runs[2].final_states[3])


def test_a_sampling_policy_draws_the_same_samples_every_run(short_parallel, roots):
    policy = mlp_actor(SCENARIO)
    runs = []
    for _ in range(2):
        torch.manual_seed(3)
        runs.append(branch_rollout(short_parallel, policy, roots, 4, 6))
    assert bitwise_equal(runs[0], runs[1]) == []
    assert not torch.equal(runs[0]["action"][0, 0], runs[0]["action"][0, 1])


def test_a_failing_policy_leaves_the_workers_ready(short_parallel, roots):
    calls = []

    def failing(td):
        calls.append(1)
        if len(calls) == 5:
            raise KeyError("policy broke")
        return ScheduledPolicy(_table())(td)

    with pytest.raises(KeyError, match="policy broke"):
        branch_rollout(short_parallel, failing, roots, 5, 6)
    # Answers still due were read: the next rollout gets its own.
    again = branch_rollout(short_parallel, ScheduledPolicy(_table()), roots, 5, 6)
    short_parallel.branch_lanes = 0
    try:
        lockstep = branch_rollout(short_parallel, ScheduledPolicy(_table()), roots, 5, 6)
    finally:
        del short_parallel.branch_lanes
    assert bitwise_equal(again, lockstep) == []


def test_a_worker_error_is_raised_with_its_traceback(short_parallel, roots):
    slots = EnvSlots(short_parallel)
    bad = ("step", 1, {("action",): np.array([[1.0, 2.0]])}, 0, False)
    short_parallel.branch_send(0, [bad], [*slots.obs_keys], slots.next_keys)
    # The worker's env refuses the action by name (InvalidActionError, a ValueError).
    with pytest.raises(RuntimeError, match="(?s)branch worker 0 failed:.*InvalidActionError"):
        short_parallel.branch_receive(0)
    data = branch_rollout(short_parallel, ScheduledPolicy(_table()), roots, 2, 3)
    assert data["mask"].any()


def test_the_last_wave_goes_to_the_workers_with_least_work_queued():
    # Steps queued per worker; horizon 8: more than half a branch above the least loaded
    # worker leaves the branch to the others; a worker with nothing queued always takes it.
    assert leave_to_others([12, 1], 0, 8)
    assert not leave_to_others([12, 1], 1, 8)
    assert not leave_to_others([5, 1], 0, 8)
    assert leave_to_others([6, 1], 0, 8)
    assert not leave_to_others([0, 9], 0, 8)
    assert leave_to_others([9, 0, 4], 0, 8) and not leave_to_others([9, 0, 4], 2, 8)
