"""Whole branches in BranchParallelEnv workers, each with its own copy of the policy."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from branching_helpers import (
    SHORT,
    ScheduledPolicy,
    bitwise_equal,
    engine,
    mixed_actions,
    mlp_actor,
    plain_env,
)
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching import branch_rollout, make_branch_env, reset_roots, shutdown_env
from torchrl_grpo.branching.dispatch import run_on
from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.policy_transport import pack_policy
from torchrl_grpo.envs import states_equal
from torchrl_grpo.modules import RandomPolicy

SCENARIO = "highway-fast-v0"
CONFIG = SHORT[SCENARIO]


def _table():
    return mixed_actions(SCENARIO)


@pytest.fixture(scope="module")
def short_parallel():
    env = make_branch_env(SCENARIO, 2, config=CONFIG, mp_start_method="fork")
    yield env
    shutdown_env(env)


@pytest.fixture(scope="module")
def short_serial():
    env = make_branch_env(SCENARIO, 2, config=CONFIG, backend="serial")
    yield env
    shutdown_env(env)


@pytest.fixture(scope="module")
def roots():
    return reset_roots(plain_env(SCENARIO, config=CONFIG), 2, seed=0)


class OutOfRange:
    """Writes an action the env does not have."""

    def __call__(self, td):
        td["action"] = torch.full(td.batch_size, 7)
        return td


class FailsAtStep2(ScheduledPolicy):
    """Raises at the third step of every branch."""

    def __call__(self, td):
        if int((td["step_count"].squeeze(-1) - td["root_step"])[0]) == 2:
            raise KeyError("policy broke")
        return super().__call__(td)


class ParentOnly(ScheduledPolicy):
    """Pickles, but refuses to be unpickled in another process."""

    def __init__(self, table):
        super().__init__(table)
        self.pid = os.getpid()

    def __setstate__(self, state):
        if state["pid"] != os.getpid():
            raise RuntimeError("this policy stays in its process")
        self.__dict__.update(state)


class ExitsOnBranch3(ScheduledPolicy):
    """Kills the worker process that runs branch 3."""

    def __call__(self, td):
        if int(td["branch"][0]) == 3:
            os._exit(1)
        return super().__call__(td)


def test_parallel_envs_run_whole_branches_in_their_workers(short_parallel, roots):
    assert EnvSlots(short_parallel).whole_branches
    policy = ScheduledPolicy(_table())
    assert branch_rollout(short_parallel, policy, roots, 5, 6)["mask"].any()
    # The workers called their copies: the parent's policy was never called.
    assert policy.calls == 0
    short_parallel.whole_branches = False
    try:
        assert not EnvSlots(short_parallel).whole_branches
    finally:
        del short_parallel.whole_branches
    serial = make_branch_env(SCENARIO, 2, config=CONFIG, backend="serial")
    assert not EnvSlots(serial).whole_branches
    shutdown_env(serial)


@pytest.mark.parametrize("return_states", [False, True])
def test_whole_branches_give_the_serial_backend_data(
    short_parallel, short_serial, roots, return_states
):
    # 10 branches of up to 6 steps on 2 workers, one and two queued per worker; short
    # episodes end some branches early. And on 1 worker.
    reference = branch_rollout(
        short_serial, ScheduledPolicy(_table()), roots, 5, 6, return_states=return_states
    )
    assert not reference["mask"].all()
    for depth in (1, 2):
        short_parallel.branch_queue_depth = depth
        try:
            data = branch_rollout(
                short_parallel, ScheduledPolicy(_table()), roots, 5, 6, return_states=return_states
            )
        finally:
            del short_parallel.branch_queue_depth
        assert bitwise_equal(reference, data) == [], depth
    one = make_branch_env(SCENARIO, 1, config=CONFIG, mp_start_method="fork")
    try:
        data = branch_rollout(
            one, ScheduledPolicy(_table()), roots, 5, 6, return_states=return_states
        )
    finally:
        shutdown_env(one)
    assert bitwise_equal(reference, data) == []


@pytest.mark.parametrize("keep", ["none", "final", "all"])
def test_every_keep_mode_matches_the_serial_engine(short_parallel, short_serial, roots, keep):
    states = roots["state"][torch.tensor([0, 0, 1, 1, 1])]
    ids = {"group_id": torch.arange(5), "branch": torch.arange(5)}
    ids["root_step"] = torch.zeros(5, dtype=torch.long)
    runs = [
        run_on(EnvSlots(env), ScheduledPolicy(_table()), states, 6, keep=keep, **ids)
        for env in (short_serial, short_parallel)
    ]
    assert bitwise_equal(runs[0].data, runs[1].data) == []
    assert torch.equal(runs[0].mask, runs[1].mask)
    assert torch.equal(runs[0].lengths, runs[1].lengths)
    assert torch.equal(runs[0].ended, runs[1].ended) and runs[0].ended.any()
    if keep == "none":
        assert runs[1].final_states is None
    else:
        assert bitwise_equal(runs[0].final_states, runs[1].final_states) == []


def test_final_states_are_the_branches_own(short_parallel, roots):
    # Each final state is the branch's: stepping its root with its actions gets there.
    states = roots["state"][torch.tensor([0, 0, 1, 1, 1])]
    ids = {"group_id": torch.arange(5), "branch": torch.arange(5)}
    ids["root_step"] = torch.zeros(5, dtype=torch.long)
    slots = EnvSlots(short_parallel)
    run = run_on(slots, ScheduledPolicy(_table()), states, 6, keep="final", **ids)
    assert run.ended.any()
    check = plain_env(SCENARIO, config=CONFIG)
    for i in range(5):
        check.set_state(states[i])
        for t in range(int(run.lengths[i])):
            check.step(TensorDict(action=_table()[i, t]))
        assert states_equal(check.get_state(), run.final_states[i]), i


def test_a_deterministic_actor_gives_the_single_env_data(short_parallel, roots):
    # The workers call the policy on one row, as a plain env's rollout does: its
    # logits are bitwise the same (a batch of W rows may round differently).
    actor = mlp_actor(SCENARIO)
    kwargs = {"return_states": True, "exploration_type": ExplorationType.DETERMINISTIC}
    single = branch_rollout(plain_env(SCENARIO, config=CONFIG), actor, roots, 3, 6, **kwargs)
    data = branch_rollout(short_parallel, actor, roots, 3, 6, **kwargs)
    assert "logits" in data.keys()
    assert bitwise_equal(single, data) == []


@pytest.mark.parametrize("make_policy", [lambda: mlp_actor(SCENARIO), lambda: RandomPolicy(seed=5)])
def test_sampling_does_not_depend_on_workers_or_queues(short_parallel, roots, make_policy):
    runs = []
    for depth in (1, 2):
        torch.manual_seed(3)
        short_parallel.branch_queue_depth = depth
        try:
            runs.append(branch_rollout(short_parallel, make_policy(), roots, 4, 6))
        finally:
            del short_parallel.branch_queue_depth
    one = make_branch_env(SCENARIO, 1, config=CONFIG, mp_start_method="fork")
    try:
        torch.manual_seed(3)
        runs.append(branch_rollout(one, make_policy(), roots, 4, 6))
    finally:
        shutdown_env(one)
    assert bitwise_equal(runs[0], runs[1]) == []
    assert bitwise_equal(runs[0], runs[2]) == []
    # Branches draw their own samples, and the next rollout draws others.
    assert not torch.equal(runs[0]["action"][0, 0], runs[0]["action"][0, 1])
    torch.manual_seed(3)
    policy = make_policy()
    first = branch_rollout(short_parallel, policy, roots, 4, 6)
    second = branch_rollout(short_parallel, policy, roots, 4, 6)
    assert bitwise_equal(first, runs[0]) == []
    assert not torch.equal(first["action"], second["action"])


def test_a_policy_generator_seed_is_kept(short_parallel, roots):
    # RandomPolicy draws from its own generator: its seed still chooses the samples.
    a = branch_rollout(short_parallel, RandomPolicy(seed=0), roots, 4, 6)
    b = branch_rollout(short_parallel, RandomPolicy(seed=1), roots, 4, 6)
    assert not torch.equal(a["action"], b["action"])


def test_a_bad_action_raises_the_single_env_error(short_parallel, short_serial, roots):
    with pytest.raises(ValueError) as single:
        branch_rollout(plain_env(SCENARIO, config=CONFIG), OutOfRange(), roots, 2, 2)
    with pytest.raises(ValueError) as parallel:
        branch_rollout(short_parallel, OutOfRange(), roots, 2, 2)
    assert "outside the env's action spec" in str(single.value)
    assert str(parallel.value) == str(single.value)
    # The workers are still usable.
    reference = branch_rollout(short_serial, ScheduledPolicy(_table()), roots, 5, 6)
    assert (
        bitwise_equal(
            reference, branch_rollout(short_parallel, ScheduledPolicy(_table()), roots, 5, 6)
        )
        == []
    )


def test_a_policy_error_in_a_worker_is_raised_in_the_parent(short_parallel, short_serial, roots):
    with pytest.raises(KeyError, match="policy broke"):
        branch_rollout(short_parallel, FailsAtStep2(_table()), roots, 5, 6)
    reference = branch_rollout(short_serial, ScheduledPolicy(_table()), roots, 5, 6)
    again = branch_rollout(short_parallel, ScheduledPolicy(_table()), roots, 5, 6)
    assert bitwise_equal(reference, again) == []


@pytest.mark.parametrize("kind", ["closure", "parent-only"])
def test_a_policy_that_cannot_go_to_the_workers_runs_in_the_parent(
    short_parallel, short_serial, roots, kind
):
    calls = []
    scheduled = ScheduledPolicy(_table())

    def closure(td):
        calls.append(1)
        return scheduled(td)

    policy = closure if kind == "closure" else ParentOnly(_table())
    data = branch_rollout(short_parallel, policy, roots, 5, 6)
    # The lock-step engine ran it, in this process.
    assert (len(calls) if kind == "closure" else policy.calls) > 0
    reference = branch_rollout(short_serial, ScheduledPolicy(_table()), roots, 5, 6)
    assert bitwise_equal(reference, data) == []


class Holds(torch.nn.Module):
    """A module holding ``thing``."""

    def __init__(self, thing):
        super().__init__()
        self.thing = thing


def test_policies_that_cannot_be_copied_to_workers_are_not_packed():
    assert pack_policy(Holds(torch.zeros(2, device="meta"))) is None
    assert pack_policy(Holds(np.random.default_rng(0))) is None
    assert pack_policy(Holds(lambda td: td)) is None
    assert pack_policy(Holds(plain_env(SCENARIO))) is None
    assert pack_policy(Holds(torch.zeros(2))) is not None
    assert pack_policy(TensorDict(a=torch.zeros(2))) is not None


def test_a_dead_worker_is_reported(roots, no_workers_left):
    env = make_branch_env(SCENARIO, 2, config=CONFIG, mp_start_method="fork")
    try:
        with engine(env, whole=True), pytest.raises(RuntimeError, match="dead"):
            branch_rollout(env, ExitsOnBranch3(_table()), roots, 5, 6)
    finally:
        shutdown_env(env)
