"""Bad input gives clear errors, leaves the env usable, and leaves no worker behind."""

from __future__ import annotations

import multiprocessing
import signal
import time
import types

import pytest
import torch
from branching_helpers import ScheduledPolicy, branch_env, plain_env
from tensordict import TensorDictBase

from torchrl_grpo.branching import (
    GroupCollector,
    StoredRoots,
    branch_rollout,
    make_roots,
    multi_turn_rollout,
    reset_roots,
    shutdown_env,
)
from torchrl_grpo.envs import StateMismatchError
from torchrl_grpo.modules import RandomPolicy


@pytest.fixture(scope="module")
def fast_roots():
    return reset_roots(plain_env("highway-fast-v0", seed=0), 1)


@pytest.mark.parametrize("group_size", [1, 0, 2.0])
def test_group_size_below_two(fast_roots, group_size):
    env = plain_env("highway-fast-v0")
    with pytest.raises(ValueError, match="group_size must be an int >= 2"):
        branch_rollout(env, RandomPolicy(), fast_roots, group_size, 3)
    with pytest.raises(ValueError, match="group_size"):
        multi_turn_rollout(env, RandomPolicy(), fast_roots, group_size, 3)


@pytest.mark.parametrize("horizon", [0, -2])
def test_horizon_below_one(fast_roots, horizon):
    env = plain_env("highway-fast-v0")
    with pytest.raises(ValueError, match="horizon must be an int >= 1"):
        branch_rollout(env, RandomPolicy(), fast_roots, 2, horizon)


def test_collector_rejects_bad_sizes_and_closes_the_given_env(no_workers_left):
    env = branch_env("merge-v0", "parallel")
    env.reset()
    assert not env.is_closed
    with pytest.raises(ValueError, match="group_size"):
        GroupCollector(env, RandomPolicy(), group_size=1, horizon=2, groups_per_batch=1)
    assert env.is_closed


def test_states_from_another_scenario(highway_parallel):
    merge_roots = reset_roots(plain_env("merge-v0", seed=0), 2)
    with pytest.raises(StateMismatchError, match="another scenario"):
        branch_rollout(highway_parallel, RandomPolicy(), merge_roots, 2, 2)
    # The workers never saw the bad states: the env still works.
    good = reset_roots(plain_env("highway-fast-v0", seed=1), 1)
    data = branch_rollout(highway_parallel, RandomPolicy(), good, 2, 2)
    assert data["mask"].all()


def test_states_from_another_config(highway_parallel):
    # Same layout (shapes and dtypes), another config: only the fingerprint tells.
    other = plain_env("highway-fast-v0", seed=0, config={"collision_reward": -2.0})
    roots = reset_roots(other, 1)
    with pytest.raises(StateMismatchError, match="another scenario or config"):
        branch_rollout(highway_parallel, RandomPolicy(), roots, 2, 2)


class _BadPolicy:
    def __init__(self, make):
        self.make = make

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td["action"] = self.make(td.batch_size)
        return td


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda b: torch.full(b, 7, dtype=torch.long), "outside the env's action spec"),
        (lambda b: torch.ones(b), "dtype torch.int64"),
        (lambda b: torch.ones(*b, 5, dtype=torch.long), "does not match the env's action spec"),
        (None, "wrote no 'action' entry"),
    ],
    ids=["out-of-range", "float", "one-hot-shape", "missing"],
)
def test_policy_output_that_does_not_fit_the_action_spec(highway_parallel, fast_roots, make, match):
    policy = _BadPolicy(make) if make is not None else (lambda td: td)
    with pytest.raises(ValueError, match=match):
        branch_rollout(highway_parallel, policy, fast_roots, 2, 2)
    # Nothing reached the workers: they still step.
    assert branch_rollout(highway_parallel, RandomPolicy(), fast_roots, 2, 2)["mask"].all()


def test_plain_env_policy_check(fast_roots):
    with pytest.raises(ValueError, match="outside"):
        branch_rollout(
            plain_env("highway-fast-v0"), _BadPolicy(lambda b: torch.full(b, -1)), fast_roots, 2, 1
        )


def test_collector_error_shuts_workers_down(no_workers_left):
    env = branch_env("merge-v0", "parallel")
    collector = GroupCollector(
        env, _BadPolicy(lambda b: torch.full(b, 9)), group_size=2, horizon=2, groups_per_batch=1
    )
    with pytest.raises(ValueError, match="outside"):
        next(iter(collector))
    assert env.is_closed


def test_collector_interrupt_shuts_workers_down(no_workers_left):
    class Interrupting(ScheduledPolicy):
        def __call__(self, td):
            if self.calls == 3:
                raise KeyboardInterrupt
            return super().__call__(td)

    env = branch_env("merge-v0", "parallel")
    collector = GroupCollector(
        env, Interrupting(torch.ones(2, 2)), group_size=2, horizon=2, groups_per_batch=2
    )
    with pytest.raises(KeyboardInterrupt):
        for _ in collector:
            pass
    assert env.is_closed


def test_collector_stored_roots_from_another_config(no_workers_left):
    roots = make_roots(reset_roots(plain_env("highway-fast-v0", seed=0), 1)["state"])
    env = branch_env("merge-v0", "parallel")
    collector = GroupCollector(
        env, RandomPolicy(), group_size=2, horizon=2, groups_per_batch=1, roots=StoredRoots(roots)
    )
    with pytest.raises(StateMismatchError):
        next(iter(collector))
    assert env.is_closed


def _ignores_sigterm(ready) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    ready.set()
    time.sleep(60)


def test_a_worker_that_outlives_sigterm_is_killed(no_workers_left):
    context = multiprocessing.get_context("spawn")
    ready = context.Event()
    worker = context.Process(target=_ignores_sigterm, args=(ready,))
    worker.start()
    assert ready.wait(60)  # SIGTERM is ignored from here on
    env = types.SimpleNamespace(is_closed=True, _workers=[worker])  # a closed env's workers
    shutdown_env(env, timeout=0.5)
    assert not worker.is_alive() and worker.exitcode == -signal.SIGKILL


def test_shutdown_is_idempotent(no_workers_left):
    env = branch_env("merge-v0", "parallel")
    env.reset()
    shutdown_env(env)
    shutdown_env(env)
    assert env.is_closed


# Each corrupts the second of a batch of states
def _zeroed_rng(states: TensorDictBase) -> None:
    states["sim", "env", "rng"][1].fill_(0)


def _nan_speed(states: TensorDictBase) -> None:
    states["sim", "entities", "f64"][1].view(torch.float64)[1].fill_(float("nan"))


def _nan_observation(states: TensorDictBase) -> None:
    states["output", "observation"][1].view(torch.float32).fill_(float("nan"))


@pytest.mark.parametrize(
    "corrupt,match",
    [(_zeroed_rng, r"env\.rng"), (_nan_speed, "entities"), (_nan_observation, "observation")],
)
def test_corrupted_roots_are_refused_and_the_workers_live_on(highway_parallel, corrupt, match):
    # Issue #20: these states hung the main process or killed the workers
    from torchrl_grpo.envs import StateCorruptedError

    roots = reset_roots(plain_env("highway-fast-v0", seed=0), 2)
    roots = roots.clone()
    corrupt(roots.get("state"))
    with pytest.raises(StateCorruptedError, match=match):
        branch_rollout(highway_parallel, RandomPolicy(), roots, 2, 2)
    good = reset_roots(plain_env("highway-fast-v0", seed=1), 1)
    data = branch_rollout(highway_parallel, RandomPolicy(), good, 2, 2)
    assert data["mask"].all()
