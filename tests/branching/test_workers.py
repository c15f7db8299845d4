"""Worker envs: the SnapshotObservation transform and make_branch_env."""

from __future__ import annotations

import time

import pytest
import torch
from branching_helpers import plain_env
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.transforms import Transform
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.branching import (
    BranchParallelEnv,
    SnapshotObservation,
    make_branch_env,
    shutdown_env,
)
from torchrl_grpo.envs import states_equal


def test_snapshot_observation_specs_and_values():
    env = TransformedEnv(plain_env("merge-v0", seed=0), SnapshotObservation())
    check_env_specs(env)
    env.reset()
    out = env.step(TensorDict(action=torch.tensor(1)))
    assert states_equal(out["next", "snapshot"], env.base_env.get_state())
    assert ("next", "state") not in out.keys(True)


def test_snapshot_observation_crosses_parallel_workers(highway_parallel):
    highway_parallel.set_seed(11)
    out = highway_parallel.reset()
    assert out["snapshot"].batch_size == (2,)
    # Two workers, two episodes (TorchRL seeds them 11 and the next seed): different states.
    assert not states_equal(out["snapshot"][0], out["snapshot"][1])


def test_make_branch_env_arguments():
    with pytest.raises(ValueError, match="backend"):
        make_branch_env("merge-v0", 2, backend="threads")
    with pytest.raises(ValueError, match="num_workers"):
        make_branch_env("merge-v0", 0)
    with pytest.raises(ValueError, match="single"):
        make_branch_env("merge-v0", 2, backend="single")
    env = make_branch_env("intersection-v0", 2, backend="serial")
    try:
        # Fixed padding: workers seeded differently still share one state layout.
        env.set_seed(3)
        out = env.reset()
        assert out["snapshot"].batch_size == (2,)
    finally:
        shutdown_env(env)


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
