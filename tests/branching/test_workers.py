"""Worker envs: make_branch_env, states through shared buffers, BranchParallelEnv."""

from __future__ import annotations

import time

import pytest
import torch
from branching_helpers import (
    SHORT,
    ScheduledPolicy,
    actions,
    bitwise_equal,
    engine,
    plain_env,
)
from tensordict import TensorDict
from torchrl.envs import ParallelEnv, TransformedEnv
from torchrl.envs.transforms import Transform

from torchrl_grpo.branching import branch_rollout, make_branch_env, reset_roots, shutdown_env
from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.workers import BranchParallelEnv
from torchrl_grpo.envs import states_equal


def test_workers_return_their_state_through_the_shared_buffers(highway_parallel):
    highway_parallel.set_seed(11)
    out = highway_parallel.reset()
    assert out["state"].batch_size == (2,)
    # Two workers, two episodes (TorchRL seeds them 11 and the next seed): different states.
    assert not states_equal(out["state"][0], out["state"][1])
    step = highway_parallel.step(out.set("action", torch.tensor([1, 1])))
    read = highway_parallel.get_state()  # one pipe round trip per worker
    for i in range(2):
        assert states_equal(step["next", "state"][i], read[i]), i


def test_make_branch_env_arguments():
    with pytest.raises(ValueError, match="backend"):
        make_branch_env("merge-v0", 2, backend="threads")
    with pytest.raises(ValueError, match="num_workers"):
        make_branch_env("merge-v0", 0)
    with pytest.raises(ValueError, match="single"):
        make_branch_env("merge-v0", 2, backend="single")
    env = make_branch_env("intersection-v0", 2, backend="serial")
    try:
        # The envs' seed-independent padding: differently seeded workers share a layout.
        env.set_seed(3)
        out = env.reset()
        assert out["state"].batch_size == (2,)
        assert states_equal(out["state"][0], plain_env("intersection-v0", seed=3).get_state())
    finally:
        shutdown_env(env)


@pytest.mark.parametrize(
    ("snapshots", "return_state", "expected"),
    [(True, None, True), (False, None, False), (False, True, True), (True, False, True)],
)
def test_snapshots_builds_workers_with_return_state(snapshots, return_state, expected):
    extra = {} if return_state is None else {"return_state": return_state}
    env = make_branch_env("merge-v0", 1, backend="single", snapshots=snapshots, **extra)
    assert env.return_state is expected
    assert ("state" in env.observation_spec.keys()) is expected


class _SlowStep(Transform):
    def _step(self, tensordict, next_tensordict):
        time.sleep(0.3)
        return next_tensordict


def _slow_env():
    return TransformedEnv(plain_env("merge-v0"), _SlowStep())


def test_branch_parallel_env_parent_sleeps_while_workers_step(no_workers_left):
    # TorchRL's ParallelEnv spins on the workers' done flags, keeping a core busy.
    env = BranchParallelEnv(1, _slow_env, mp_start_method="fork")
    try:
        env.reset()
        action = TensorDict(action=torch.tensor([1]), batch_size=[1])
        cpu, wall = time.process_time(), time.perf_counter()
        out = env.step(action)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    finally:
        shutdown_env(env)
    assert wall >= 0.3
    assert cpu < 0.3 * wall, f"parent used {cpu:.3f} s of CPU in {wall:.3f} s"
    assert out["next", "observation"].shape[0] == 1


def test_branch_parallel_env_falls_back_to_torchrl_wait(no_workers_left, monkeypatch):
    # Without the attributes it was written against (pipe mode here), or when turned
    # off, TorchRL's own wait runs: the env still steps.
    calls = []
    original = ParallelEnv._wait_for_workers

    def spy(self, workers_range):
        calls.append(type(self).__name__)
        return original(self, workers_range)

    monkeypatch.setattr(ParallelEnv, "_wait_for_workers", spy)
    for kwargs, off in (({"use_buffers": False}, False), ({}, True)):
        env = BranchParallelEnv(1, _slow_env, mp_start_method="fork", **kwargs)
        env.sleep_while_waiting = not off
        try:
            env.reset()
            assert not env._sleeping_wait_applies()
            out = env.step(TensorDict(action=torch.tensor([1]), batch_size=[1]))
        finally:
            shutdown_env(env)
        assert out["next", "observation"].shape[0] == 1
    assert calls, "TorchRL's own wait was not used"


def test_branch_parallel_env_uses_its_wait_on_this_torchrl(highway_parallel):
    # The attributes the sleeping wait needs are there on the pinned TorchRL version,
    # once the workers run (the shared fixture starts them at its first use, which is
    # this test when it runs first).
    assert isinstance(highway_parallel, BranchParallelEnv)
    if highway_parallel.is_closed:
        highway_parallel.start()
    assert highway_parallel._sleeping_wait_applies()


@pytest.mark.parametrize("return_states", [False, True])
def test_branch_fast_paths_match_torchrl_reset_and_step(highway_parallel, return_states):
    # branch_restore / branch_step move only what a rollout reads; TorchRL's reset and
    # step move everything. 5 branches on 2 workers: partial steps in the last wave;
    # short episodes: branches end early, slots refill mid-rollout.
    assert EnvSlots(highway_parallel)._fast
    roots = reset_roots(plain_env("highway-fast-v0", config=SHORT["highway-fast-v0"]), 1, seed=0)
    table = actions(
        "highway-fast-v0",
        ["FASTER"] * 6,
        ["LANE_LEFT", "SLOWER"] * 3,
        ["IDLE"] * 6,
        ["LANE_RIGHT", "FASTER"] * 3,
        ["SLOWER"] * 6,
    )
    env = make_branch_env(
        "highway-fast-v0", 2, config=SHORT["highway-fast-v0"], mp_start_method="fork"
    )
    try:
        fast = {}
        for name, whole in (("whole", True), ("lockstep", False)):
            with engine(env, whole=whole):
                fast[name] = branch_rollout(
                    env, ScheduledPolicy(table), roots, 5, 6, return_states=return_states
                )
        env.branch_fast_paths = False
        assert not EnvSlots(env)._fast
        slow = branch_rollout(env, ScheduledPolicy(table), roots, 5, 6, return_states=return_states)
    finally:
        shutdown_env(env)
    assert not slow["mask"].all()
    for name, data in fast.items():
        assert bitwise_equal(data, slow) == [], name


def test_sleeping_wait_learns_the_wait_lengths(highway_parallel):
    # After a few steps, a step's wait starts with one long sleep: a handful of
    # wake-ups per wait instead of one every 0.5 ms (the lock-step path).
    roots = reset_roots(plain_env("highway-fast-v0"), 1, seed=0)
    with engine(highway_parallel, whole=False):
        branch_rollout(highway_parallel, ScheduledPolicy(torch.ones(2, 4)), roots, 2, 4)
    recent = highway_parallel.__dict__["_recent_waits"]
    assert recent["step"] > 0 and recent["restore"] > 0
    assert highway_parallel.__dict__.get("_wait_kind") is None


def test_make_branch_env_branches_cartpole_by_id_and_by_factory():
    import functools

    from torchrl_grpo.envs import SnapshotEnv

    class Alternate:
        """Pushes left on even branches, right on odd ones."""

        def __call__(self, td):
            return td.set("action", (td["branch"] % 2).to(torch.int64))

    runs = []
    for env_arg, backend in [
        ("CartPole-v1", "serial"),
        ("CartPole-v1", "parallel"),
        (functools.partial(SnapshotEnv, "CartPole-v1"), "parallel"),
    ]:
        extra = {"mp_start_method": "fork"} if backend == "parallel" else {}
        env = make_branch_env(env_arg, 2, backend=backend, **extra)
        try:
            roots = reset_roots(env, 2, seed=3)
            runs.append(branch_rollout(env, Alternate(), roots, group_size=2, horizon=6))
        finally:
            shutdown_env(env)
    for other in runs[1:]:
        assert bitwise_equal(runs[0], other) == []
    obs = runs[0]["next", "observation"]
    assert not torch.equal(obs[:, 0], obs[:, 1])  # the two actions lead apart


def test_make_branch_env_takes_a_highway_factory_and_refuses_bad_ids():
    import functools

    from torchrl_grpo.envs import HighwayEnv

    env = make_branch_env(functools.partial(HighwayEnv, "merge-v0"), 1, backend="single")
    assert "state" in env.observation_spec.keys()
    with pytest.raises(KeyError, match="no state codec"):
        make_branch_env("Pendulum-v1", 1, backend="single")
    with pytest.raises(ValueError, match="config"):
        make_branch_env("CartPole-v1", 1, backend="single", config={"x": 1})
