"""TensorHighwayEnv("roundabout-v0"): specs, highway-env's resets, routes, the bridge, errors."""

from __future__ import annotations

import pytest
import torch
from env_helpers import assert_branches_match_highway_env, visited_states
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import HighwayEnv, StateCorruptedError, TensorHighwayEnv, state_differences

SCENARIO = "roundabout-v0"


@pytest.mark.parametrize("kwargs", [{}, {"dtype": torch.float64, "return_state": True}])
def test_check_env_specs(kwargs):
    check_env_specs(TensorHighwayEnv(SCENARIO, num_envs=4, seed=0, **kwargs))


def test_fresh_worlds_are_highway_envs_own_episodes():
    # Row i of seed s is highway-env's reset(seed=s + i) (numpy's normals, drawn on the
    # host), and its next episode the generator's next reset: bit for bit, routes included.
    env = TensorHighwayEnv(SCENARIO, num_envs=3, seed=11, dtype=torch.float64)
    env.reset()
    first = env.state_to_highway(env.get_state())
    env.reset()
    second = env.state_to_highway(env.get_state())
    for i in range(3):
        hw = HighwayEnv(SCENARIO, seed=11 + i)
        hw.reset()
        assert state_differences(first[i], hw.get_state()) == [], i
        hw.reset()
        assert state_differences(second[i], hw.get_state()) == [], i


def test_routes_are_highway_envs_and_advance_as_it_drops_legs():
    env = TensorHighwayEnv(SCENARIO, num_envs=1, seed=0, dtype=torch.float64)
    hw = HighwayEnv(SCENARIO, seed=0)
    hw.reset()
    td = env.reset()
    for _ in range(4):  # FASTER: the ego enters the ring and drops its first legs
        td = env.step(td.set("action", torch.tensor([3])))["next"]
        hw.step(TensorDict(action=torch.tensor(3)))
    core = hw.gym_env.unwrapped
    state = env.get_state()
    heads = state["route", "head"][0]
    assert int(heads[0]) >= 2  # (ser, ses) and (ses, se) are behind the ego
    back = env.state_to_highway(state)[0]
    hw2 = HighwayEnv(SCENARIO)
    hw2.set_state(back)
    routes = [v.route for v in hw2.gym_env.unwrapped.road.vehicles]
    assert routes == [v.route for v in core.road.vehicles]


LAST_ACTION = ("output", "reward_components", "lane_change_reward")


def test_round_trip_from_highway_env_is_bitwise():
    states = visited_states(SCENARIO, 5, steps=8)
    env = TensorHighwayEnv(SCENARIO, num_envs=1, dtype=torch.float64)
    back = env.state_to_highway(env.state_from_highway(states))
    for i in range(states.shape[0]):
        # The tensor state holds the world, not the last action's cached reward term.
        assert state_differences(states[i], back[i]) in ([], [str(LAST_ACTION)]), i


def test_tensor_steps_continue_in_highway_env():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=4, dtype=torch.float64)
    env.reset()
    env.step(TensorDict(action=torch.tensor([3, 1]), batch_size=[2]))
    state = env.get_state()
    hw = HighwayEnv(SCENARIO)
    hw.set_state(env.state_to_highway(state)[0])
    hw_next = hw.step(TensorDict(action=torch.tensor(0)))["next"]
    td = env.step(TensorDict(action=torch.tensor([0, 0]), batch_size=[2]))["next"]
    assert torch.allclose(td["observation"][0].float(), hw_next["observation"], atol=1e-6)
    assert abs(float(td["reward"][0]) - float(hw_next["reward"])) < 1e-6


def test_branch_rollout_runs_rows_as_highway_env_does():
    assert_branches_match_highway_env(SCENARIO, 3, 5)  # always FASTER


def test_episodes_are_truncated_at_the_duration():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    policy = lambda td: td.set("action", torch.full((2,), 4))  # noqa: E731 - SLOWER: no crash
    td = env.rollout(11, policy, break_when_any_done=False)
    truncated = td["next", "truncated"].squeeze(-1)
    assert truncated[:, -1].all() and not truncated[:, :-1].any()


@pytest.mark.parametrize(
    ("config", "match"),
    [
        ({"incoming_vehicle_destination": 1}, "incoming_vehicle_destination"),
        ({"lanes_count": 3}, "unknown config key 'lanes_count'"),
        ({"observation": {"type": "Kinematics"}}, "features_range"),
        ({"collision_reward": 0.2}, "collision_reward"),
    ],
)
def test_uncovered_configs_are_value_errors_naming_the_key(config, match):
    with pytest.raises(ValueError, match=match):
        TensorHighwayEnv(SCENARIO, config)


def test_a_bad_route_is_refused_naming_it_and_the_env_stays_usable():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    state = env.get_state()
    state["route", "legs"][1, 2, 0] = 99  # 32 lanes and 24 roads: codes 0..55
    with pytest.raises(StateCorruptedError, match="route.legs"):
        env.reset(TensorDict(state=state, batch_size=[2]), set_state=True)
    env.rollout(2)
