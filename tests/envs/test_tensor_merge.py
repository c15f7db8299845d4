"""TensorHighwayEnv("merge-v0"): specs, highway-env's own resets, the bridge, branches, errors."""

from __future__ import annotations

import pytest
import torch
from env_helpers import assert_branches_match_highway_env, visited_states
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv, state_differences

SCENARIO = "merge-v0"


@pytest.mark.parametrize("kwargs", [{}, {"dtype": torch.float64, "return_state": True}])
def test_check_env_specs(kwargs):
    check_env_specs(TensorHighwayEnv(SCENARIO, num_envs=4, seed=0, **kwargs))


def test_fresh_worlds_are_highway_envs_own_episodes():
    # Row i of seed s is highway-env's reset(seed=s + i), and its next episode the
    # generator's next reset: bit for bit, through the bridge.
    env = TensorHighwayEnv(SCENARIO, num_envs=3, seed=11, dtype=torch.float64)
    env.reset()
    first = env.state_to_highway(env.get_state())
    env.reset()  # every row: its second episode
    second = env.state_to_highway(env.get_state())
    for i in range(3):
        hw = HighwayEnv(SCENARIO, seed=11 + i)
        hw.reset()
        assert state_differences(first[i], hw.get_state()) == [], i
        hw.reset()
        assert state_differences(second[i], hw.get_state()) == [], i


LAST_ACTION = ("output", "reward_components", "lane_change_reward")


def test_round_trip_from_highway_env_is_bitwise():
    states = visited_states(SCENARIO, 5, steps=10)
    env = TensorHighwayEnv(SCENARIO, num_envs=1, dtype=torch.float64)
    back = env.state_to_highway(env.state_from_highway(states))
    lost = 0
    for i in range(states.shape[0]):
        # The tensor state holds the world, not the last action: a restored state's
        # cached lane-change term reads 0 (its next step computes it again).
        diff = state_differences(states[i], back[i])
        lost += diff == [str(LAST_ACTION)]
        assert diff in ([], [str(LAST_ACTION)]), i
        assert float(back[i][LAST_ACTION].view(torch.float32)) == 0.0 or not diff
    assert lost < states.shape[0]


def test_tensor_steps_continue_in_highway_env_and_render():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=4, dtype=torch.float64)
    env.reset()
    env.step(TensorDict(action=torch.tensor([3, 1]), batch_size=[2]))
    state = env.get_state()
    hw = HighwayEnv(SCENARIO)
    hw.set_state(env.state_to_highway(state)[0])
    hw_next = hw.step(TensorDict(action=torch.tensor(2)))["next"]
    td = env.step(TensorDict(action=torch.tensor([2, 2]), batch_size=[2]))["next"]
    assert torch.allclose(td["observation"][0].float(), hw_next["observation"], atol=1e-6)
    assert abs(float(td["reward"][0]) - float(hw_next["reward"])) < 1e-6  # float32 there
    frames = env.render_frames(state)
    assert len(frames) == 2 and frames[0].ndim == 3 and frames[0].std() > 0


def test_rollout_resets_finished_rows_into_new_episodes():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    state = env.get_state()
    # Row 0's ego 25 m before the end of the ramp zone (x > 370 ends the episode).
    state["vehicles", "x"][0, 0] = 350.0
    state["vehicles", "lane"][0, 0] = state["vehicles", "target_lane"][0, 0] = 6  # (c, d, 1)
    td = env.reset(TensorDict(state=state, batch_size=[2]), set_state=True)
    policy = lambda td: td.set("action", torch.full((2,), 1))  # noqa: E731 - IDLE
    td = env.rollout(3, policy, break_when_any_done=False, auto_reset=False, tensordict=td)
    done = td["next", "done"].squeeze(-1)
    assert done[0].tolist() == [True, False, False] and not bool(done[1].any())
    # The next step starts a fresh episode: the ego back near its spawn (x = 30).
    assert float(td["next", "ego_position"][0, 1, 0]) < 100.0


def test_branch_rollout_runs_rows_as_highway_env_does():
    assert_branches_match_highway_env(SCENARIO, 3, 6)  # always FASTER


@pytest.mark.parametrize(
    ("config", "match"),
    [
        ({"other_vehicles_type": "highway_env.vehicle.behavior.LinearVehicle"}, "other_vehicles"),
        ({"lanes_count": 3}, "unknown config key 'lanes_count'"),
        ({"observation": {"type": "Kinematics", "features_range": {"x": [5, 5]}}},
         "features_range"),
        ({"collision_reward": -0.5, "merging_speed_reward": 0.0, "high_speed_reward": -0.6,
          "right_lane_reward": 0.1}, "collision_reward"),
    ],
)  # fmt: skip
def test_uncovered_configs_are_value_errors_naming_the_key(config, match):
    with pytest.raises(ValueError, match=match):
        TensorHighwayEnv(SCENARIO, config)


def test_covered_overrides_change_the_reward():
    base = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0, dtype=torch.float64)
    other = TensorHighwayEnv(SCENARIO, {"lane_change_reward": -0.5}, num_envs=2, seed=0,
                             dtype=torch.float64)  # fmt: skip
    action = TensorDict(action=torch.tensor([0, 1]), batch_size=[2])
    a, b = base.step(action.clone())["next", "reward"], other.step(action.clone())["next", "reward"]
    assert float(a[1]) == float(b[1]) and float(a[0]) != float(b[0])


def test_compile_leaves_the_merge_step_eager():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    assert env.compile() is env
    env.rollout(2)


def test_reseeded_rows_draw_highway_envs_episode_of_that_seed():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0, dtype=torch.float64)
    state = env.reseed_state(env.get_state(), [5, 6])
    env.reset(TensorDict(state=state, batch_size=[2]), set_state=True)
    env.reset()
    hw = HighwayEnv(SCENARIO, seed=6)
    hw.reset()
    assert state_differences(env.state_to_highway(env.get_state())[1], hw.get_state()) == []


def test_a_bad_lane_is_refused_naming_it_and_the_env_stays_usable():
    from torchrl_grpo.envs import StateCorruptedError

    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    state = env.get_state()
    state["vehicles", "lane"][1, 2] = 9  # the merge road has lanes 0..8
    with pytest.raises(StateCorruptedError, match="vehicles.lane"):
        env.reset(TensorDict(state=state, batch_size=[2]), set_state=True)
    env.rollout(2)


def test_a_car_driving_into_the_obstacle_crashes_as_in_highway_env():
    from torchrl_grpo.sim.state import world_from_tensordict

    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0, dtype=torch.float64)
    state = env.get_state()
    # Row 0: the ego on the merge lane (b, c, 2), 12 m before the obstacle at (310, 8);
    # row 1: the merging car there instead.
    for row, vehicle in ((0, 0), (1, 4)):
        state["vehicles", "x"][row, vehicle] = 298.0
        state["vehicles", "y"][row, vehicle] = 8.0
        state["vehicles", "lane"][row, vehicle] = 4
        state["vehicles", "target_lane"][row, vehicle] = 4
    env.reset(TensorDict(state=state, batch_size=[2]), set_state=True)
    before = env.state_to_highway(env.get_state())
    td = env.step(TensorDict(action=torch.tensor([1, 1]), batch_size=[2]))["next"]
    mine = world_from_tensordict(env.get_state()).vehicles
    hw = HighwayEnv(SCENARIO)
    for row in range(2):
        hw.set_state(before[row])
        hw.step(TensorDict(action=torch.tensor(1)))
        assert hw.gym_env.unwrapped.road.objects[0].crashed  # the obstacle is hit in both
        ref = world_from_tensordict(env.state_from_highway(hw.get_state().unsqueeze(0))).vehicles
        for name in ("x", "y", "heading", "speed", "impact_x", "impact_y"):
            assert torch.allclose(getattr(mine, name)[row], getattr(ref, name)[0], atol=1e-9)
        for name in ("crashed", "impact", "lane", "target_lane"):
            assert torch.equal(getattr(mine, name)[row], getattr(ref, name)[0]), name
    assert bool(td["crashed"][0]) and not bool(td["crashed"][1])
    assert bool(mine.crashed[1, 4]) and bool(mine.crashed[:, 5].all())
