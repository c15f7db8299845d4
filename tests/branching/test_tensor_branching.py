"""Branch rollouts on the batched simulator: the R x G branches are rows of one rollout."""

from __future__ import annotations

import pytest
import torch
from branching_helpers import ScheduledPolicy, actions

from torchrl_grpo.branching import (
    BRANCH_RETURN,
    GROUP_ID,
    MASK,
    branch_rollout,
    final_states,
    make_roots,
    reset_roots,
)
from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv


@pytest.fixture(scope="module")
def highway_roots():
    env = HighwayEnv("highway-fast-v0")
    return reset_roots(env, 3, seed=5)


def schedule():
    # Branch 0 accelerates into traffic, 1 idles, 2 brakes, 3 changes lanes and back.
    return ScheduledPolicy(
        actions(
            "highway-fast-v0",
            ["FASTER"] * 12,
            ["IDLE"] * 12,
            ["SLOWER"] * 12,
            ["LANE_LEFT", "IDLE", "LANE_RIGHT"] * 4,
        )
    )


@pytest.mark.parametrize("rows", [12, 5])  # every branch at once; waves of 5 rows
def test_tensor_branches_match_highway_env_branches(highway_roots, rows):
    highway = branch_rollout(HighwayEnv("highway-fast-v0"), schedule(), highway_roots, 4, 12)
    env = TensorHighwayEnv("highway-fast-v0", num_envs=rows, dtype=torch.float64)
    roots = make_roots(env.state_from_highway(highway_roots["state"]))
    tensor = branch_rollout(env, schedule(), roots, 4, 12)
    assert tensor.batch_size == highway.batch_size == torch.Size([3, 4, 12])
    assert torch.equal(tensor[MASK], highway[MASK])
    assert torch.equal(tensor[GROUP_ID], highway[GROUP_ID])
    for key in [("next", "done"), ("next", "truncated"), ("next", "crashed"), "action"]:
        assert torch.equal(tensor[key], highway[key]), key
    mask = highway[MASK]
    for key in [("next", "observation"), ("next", "reward"), BRANCH_RETURN]:
        a, b = tensor[key][mask].double(), highway[key][mask].double()
        assert torch.allclose(a, b, atol=1e-5), key
    assert bool(highway[("next", "crashed")].any())  # the FASTER branches crash: masks matter


def test_steps_after_an_end_are_zeros_and_states_are_kept():
    env = TensorHighwayEnv("highway-fast-v0", num_envs=8, seed=1)
    roots = make_roots(env.get_state()[:2])
    data = branch_rollout(env, schedule(), roots, 4, 12, return_states=True)
    mask = data[MASK]
    assert bool((~mask).any())
    assert float(data["next", "reward"][~mask].abs().sum()) == 0.0
    finals = final_states(data)
    assert finals.batch_size == torch.Size([2, 4])
    env.validate_state(finals.reshape(-1))
    # The state kept before step 0 is the root itself.
    assert torch.equal(data["state", "vehicles", "x"][:, 0, 0], roots["state", "vehicles", "x"])


def test_per_branch_reseeding_keeps_the_worlds():
    env = TensorHighwayEnv("highway-fast-v0", num_envs=8, seed=2)
    roots = make_roots(env.get_state()[:2])
    shared = branch_rollout(env, schedule(), roots, 4, 6)
    reseeded = branch_rollout(env, schedule(), roots, 4, 6, rng="per_branch", seed=3)
    # Steps draw nothing: the same actions give the same branches.
    assert torch.equal(shared["next", "observation"], reseeded["next", "observation"])


def test_states_are_kept_only_when_asked_as_on_highway_env(highway_roots):
    # The training env writes its state into every step (return_state=True); branch data
    # holds states only with return_states=True, as the worker-slot engines return them.
    highway = branch_rollout(HighwayEnv("highway-fast-v0"), schedule(), highway_roots, 4, 3)
    env = TensorHighwayEnv("highway-fast-v0", num_envs=12, return_state=True)
    roots = make_roots(env.state_from_highway(highway_roots["state"]))
    plain = branch_rollout(env, schedule(), roots, 4, 3)
    assert "state" not in plain.keys() and "state" not in plain["next"].keys()
    assert set(plain.keys(True, True)) == set(highway.keys(True, True))
    kept = branch_rollout(env, schedule(), roots, 4, 3, return_states=True)
    assert torch.equal(kept["next", "observation"], plain["next", "observation"])
    assert "state" in kept.keys() and "state" in kept["next"].keys()
