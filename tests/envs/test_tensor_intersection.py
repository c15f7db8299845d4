"""TensorHighwayEnv("intersection-v0"): specs, highway-env's episodes, the bridge, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from env_helpers import assert_branches_match_highway_env, visited_states
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import (
    HighwayEnv,
    InvalidActionError,
    StateCorruptedError,
    TensorHighwayEnv,
    state_differences,
)
from torchrl_grpo.sim.state import Vehicles, world_from_tensordict

SCENARIO = "intersection-v0"
# highway-env observes before the exits and the spawn of a step: the state's cached
# observation is that one, and a world written back observes after them.
OBSERVED = str(("output", "observation"))


@pytest.mark.parametrize("kwargs", [{}, {"dtype": torch.float64, "return_state": True}])
def test_check_env_specs(kwargs):
    env = TensorHighwayEnv(SCENARIO, num_envs=4, seed=0, **kwargs)
    check_env_specs(env)
    assert env.action_spec.space.n == 3  # SLOWER, IDLE, FASTER


def assert_same_world(tensor_state, highway_state, bridge):
    """The same vehicles (floats to 1e-9: the reset simulates 3 s), routes and generator."""
    mine, words, _ = bridge.read(highway_state)
    theirs = world_from_tensordict(tensor_state.unsqueeze(0))
    for name in Vehicles._fields:
        a, b = getattr(mine.vehicles, name), getattr(theirs.vehicles, name)
        used = mine.vehicles.present | theirs.vehicles.present
        if a.is_floating_point():
            assert float((a - b.double()).abs()[used].max()) <= 1e-9, name
        else:
            assert torch.equal(a[used], b[used]), name
    assert torch.equal(mine.ego_rank, theirs.ego_rank)
    assert torch.equal(mine.yielding, theirs.yielding) and torch.equal(
        mine.road_steps, theirs.road_steps
    )
    assert torch.equal(words[0], tensor_state["highway", "rng"])


def test_fresh_worlds_are_highway_envs_own_episodes():
    # Row i of seed s is highway-env's reset(seed=s + i): the spawns, 3 s of traffic with
    # the right-of-way rules, the challenger and the ego; and its next reset the next.
    env = TensorHighwayEnv(SCENARIO, num_envs=3, seed=11, dtype=torch.float64)
    env.reset()
    first = env.get_state()
    env.reset()
    second = env.get_state()
    for i in range(3):
        hw = HighwayEnv(SCENARIO, seed=11 + i)
        hw.reset()
        assert_same_world(first[i], hw.get_state(), env.bridge)
        hw.reset()
        assert_same_world(second[i], hw.get_state(), env.bridge)


def test_episodes_replay_highway_env_with_its_spawns():
    # Each step's spawn draws from highway-env's own generator, carried in the state: the
    # same rewards, flags and vehicles to the end of every episode.
    n, seed = 6, 40
    env = TensorHighwayEnv(SCENARIO, num_envs=n, seed=seed, dtype=torch.float64)
    td = env.reset()
    highway = [HighwayEnv(SCENARIO, seed=seed + i) for i in range(n)]
    for hw in highway:
        hw.reset()
    rng = np.random.default_rng(0)
    alive = torch.ones(n, dtype=torch.bool)
    spawned = 0
    for _ in range(13):
        actions = torch.from_numpy(rng.integers(3, size=n))
        before = env.get_state()["vehicles", "present"].sum(1)
        td = env.step(td.set("action", actions))["next"]
        spawned += int((env.get_state()["vehicles", "present"].sum(1) > before).sum())
        for i, hw in enumerate(highway):
            if not alive[i]:
                continue
            ref = hw.step(TensorDict(action=actions[i]))["next"]
            assert abs(float(td["reward"][i]) - float(ref["reward"])) < 1e-6, i
            assert torch.allclose(td["observation"][i].float(), ref["observation"], atol=1e-6)
            assert bool(td["done"][i]) == bool(ref["done"]), i
            alive[i] = not bool(ref["done"])
        if not bool(alive.any()):
            break
    assert spawned > 0


def test_round_trip_from_highway_env_keeps_every_simulated_bit():
    states = visited_states(SCENARIO, 3, steps=10)
    env = TensorHighwayEnv(SCENARIO, num_envs=1, dtype=torch.float64)
    back = env.state_to_highway(env.state_from_highway(states))
    for i in range(states.shape[0]):
        assert state_differences(states[i], back[i]) in ([], [OBSERVED]), i
    # The ego comes after the reset's vehicles in road order, and yields are kept.
    ranks = env.state_from_highway(states)["ego_rank"]
    assert bool((ranks > 0).all())


def test_tensor_steps_continue_in_highway_env():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=4, dtype=torch.float64)
    env.reset()
    env.step(TensorDict(action=torch.tensor([2, 1]), batch_size=[2]))
    hw = HighwayEnv(SCENARIO)
    hw.set_state(env.state_to_highway(env.get_state())[0])
    hw_next = hw.step(TensorDict(action=torch.tensor(0)))["next"]
    td = env.step(TensorDict(action=torch.tensor([0, 0]), batch_size=[2]))["next"]
    assert torch.allclose(td["observation"][0].float(), hw_next["observation"], atol=1e-6)
    assert abs(float(td["reward"][0]) - float(hw_next["reward"])) < 1e-6


def test_partial_steps_keep_the_other_rows_and_their_generators():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=1, dtype=torch.float64)
    env.reset()
    before = env.get_state()
    step = TensorDict(
        action=torch.tensor([2, 2]), _step=torch.tensor([True, False]), batch_size=[2]
    )
    env.step(step)
    after = env.get_state()
    assert state_differences(after[1], before[1]) == []
    assert not torch.equal(after["steps"][0], before["steps"][0])


def test_branch_rollout_runs_rows_as_highway_env_does():
    assert_branches_match_highway_env(SCENARIO, 2, 5)  # always FASTER


def test_render_frames_draws_through_highway_env():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    frames = env.render_frames(env.get_state())
    assert len(frames) == 2 and frames[0].ndim == 3 and frames[0].shape[-1] == 3


@pytest.mark.parametrize(
    ("config", "match"),
    [
        ({"destination": "o0"}, "destination"),
        ({"initial_vehicle_count": 1}, "initial_vehicle_count"),
        ({"spawn_probability": 1.5}, "spawn_probability"),
        ({"controlled_vehicles": 2}, "controlled_vehicles"),
        ({"action": {"type": "DiscreteMetaAction", "lateral": True}}, "action.lateral"),
        ({"lanes_count": 3}, "unknown config key 'lanes_count'"),
    ],
)
def test_uncovered_configs_are_value_errors_naming_the_key(config, match):
    with pytest.raises(ValueError, match=match):
        TensorHighwayEnv(SCENARIO, config)


def test_a_drawn_destination_is_highway_envs():
    config = {"destination": None}
    env = TensorHighwayEnv(SCENARIO, config, num_envs=4, seed=5, dtype=torch.float64)
    env.reset()
    state = env.get_state()
    for i in range(4):
        assert_same_world(
            state[i], HighwayEnv(SCENARIO, config, seed=5 + i).get_state(), env.bridge
        )


def test_an_action_of_the_five_meta_actions_is_refused_and_the_env_stays_usable():
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    before = env.get_state()
    with pytest.raises(InvalidActionError):
        env.step(TensorDict(action=torch.tensor([1, 3]), batch_size=[2]))
    assert state_differences(env.get_state()[0], before[0]) == []
    env.rollout(2)


@pytest.mark.parametrize(
    ("entry", "value", "match"),
    [("ego_rank", 30, "ego_rank"), ("yielding", 5, "yielding"), ("road_steps", -1, "road_steps")],
)
def test_a_bad_intersection_field_is_refused_naming_it(entry, value, match):
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0)
    state = env.get_state()
    state[entry][1] = value
    with pytest.raises(StateCorruptedError, match=match):
        env.reset(TensorDict(state=state, batch_size=[2]), set_state=True)
    env.rollout(2)
