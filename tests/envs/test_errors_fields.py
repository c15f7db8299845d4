"""Bad input, continued: state capacity, unknown fields and classes, construction and reset.

As in test_errors.py, after every error the env's state is compared bitwise with its
state before, and the env then steps alongside a twin that never saw the error.
"""

from __future__ import annotations

import pytest
import torch
from env_helpers import (
    assert_bitwise_equal,
    careful_actions,
    faithful_copy,
)
from error_helpers import (
    SCENARIO,
    UnregisteredIDM,
    assert_untouched,
    warmed_up,
)
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.objects import Obstacle
from tensordict import TensorDict

from torchrl_grpo.envs import (
    HighwayEnv,
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    UnknownFieldError,
)


# ---------------------------------------------------------------- capacity
def test_more_spawned_vehicles_than_padding():
    probe = HighwayEnv("intersection-v0", seed=0)
    n = len(probe.gym_env.unwrapped.road.vehicles)
    env = HighwayEnv("intersection-v0", seed=0, max_vehicles=n)
    twin = HighwayEnv("intersection-v0", seed=0, max_vehicles=40)
    actions = careful_actions(env, 40)
    for t, action in enumerate(actions):
        out = env.step(TensorDict(action=action))["next"]
        ref = twin.step(TensorDict(action=action))["next"]
        assert_bitwise_equal(out, ref, f"step {t}")
        if len(env.gym_env.unwrapped.road.vehicles) > n:
            break
    else:
        pytest.fail("intersection-v0 never spawned beyond its initial count")
    with pytest.raises(StateCapacityError, match=rf"{n}.*max_vehicles"):
        env.get_state()
    for action in actions[t + 1 : t + 6]:  # still steps exactly like its twin
        out = env.step(TensorDict(action=action))["next"]
        ref = twin.step(TensorDict(action=action))["next"]
        assert_bitwise_equal(out, ref, "step after the capacity error")


@pytest.mark.parametrize("what", ["vehicles", "objects"])
def test_appended_road_objects_beyond_padding(what, env_and_twin):
    env, twin = env_and_twin
    before = env.get_state()
    road = env.gym_env.unwrapped.road
    if what == "vehicles":
        extra = [IDMVehicle.create_from(road.vehicles[1]) for _ in range(env.codec.max_vehicles)]
        road.vehicles.extend(extra)
    else:
        extra = [Obstacle(road, [10.0 * i, 0.0]) for i in range(env.codec.max_objects + 1)]
        road.objects.extend(extra)
    with pytest.raises(StateCapacityError, match=f"max_{what}"):
        env.get_state()
    del getattr(road, what)[-len(extra) :]
    assert_untouched(env, before, twin)


# ---------------------------------------------------------------- unknown fields and classes
def test_unknown_vehicle_attribute_names_itself(env_and_twin):
    env, twin = env_and_twin
    before = env.get_state()
    vehicle = env.gym_env.unwrapped.road.vehicles[1]
    vehicle.my_field = 1.0
    with pytest.raises(UnknownFieldError, match=r"IDMVehicle\.my_field"):
        env.get_state()
    del vehicle.my_field
    assert_untouched(env, before, twin)


def test_registered_field_with_a_value_of_the_wrong_kind(env_and_twin):
    env, twin = env_and_twin
    before = env.get_state()
    vehicle = env.gym_env.unwrapped.road.vehicles[1]
    timer = vehicle.timer
    vehicle.timer = "soon"
    with pytest.raises(UnknownFieldError, match="timer"):
        env.get_state()
    vehicle.timer = timer
    assert_untouched(env, before, twin)


def test_unknown_env_attribute_names_itself(env_and_twin):
    env, twin = env_and_twin
    before = env.get_state()
    core = env.gym_env.unwrapped
    core.my_flag = True
    with pytest.raises(UnknownFieldError, match="my_flag"):
        env.get_state()
    del core.my_flag
    assert_untouched(env, before, twin)


def test_unregistered_vehicle_class_names_itself(env_and_twin):
    env, twin = env_and_twin
    before = env.get_state()
    road = env.gym_env.unwrapped.road
    original = road.vehicles[2]
    road.vehicles[2] = UnregisteredIDM.create_from(original)
    with pytest.raises(UnknownFieldError, match="UnregisteredIDM"):
        env.get_state()
    road.vehicles[2] = original
    assert_untouched(env, before, twin)


def test_return_state_step_reports_an_unknown_field():
    env = warmed_up(return_state=True)
    env.gym_env.unwrapped.road.vehicles[1].my_field = 1.0
    with pytest.raises(UnknownFieldError, match="my_field"):
        env.step(TensorDict(action=torch.tensor(1)))


# ---------------------------------------------------------------- construction and reset
def test_unknown_scenario_names_itself_and_suggests():
    with pytest.raises(ValueError, match=r"'highway-fst-v0'.*highway-fast-v0"):
        HighwayEnv("highway-fst-v0")
    with pytest.raises(ValueError, match="nonsense"):
        HighwayEnv("nonsense")


def test_unknown_config_key_names_itself_and_suggests():
    with pytest.raises(ValueError, match=r"'lane_count'.*'lanes_count'"):
        HighwayEnv(SCENARIO, config={"lane_count": 3})
    with pytest.raises(ValueError, match="not_a_key"):
        HighwayEnv("parking-v0", config={"not_a_key": 1})


@pytest.mark.parametrize(
    "given",
    [None, TensorDict(), TensorDict(other=torch.zeros(1))],
    ids=["nothing", "empty", "no-state-entry"],
)
def test_set_state_without_a_state(given, env_and_twin):
    env, twin = env_and_twin
    before = env.get_state()
    with pytest.raises(SnapshotError, match="'state'"):
        env.reset(given, set_state=True)
    assert_untouched(env, before, twin)


def test_validate_state_checks_every_state_of_a_batch(env_and_twin):
    env, _ = env_and_twin
    good = env.get_state()
    bad = faithful_copy(good)
    bad["sim", "env", "time"].view(torch.float64).fill_(float("inf"))
    env.validate_state(torch.stack([good, good]))
    with pytest.raises(StateCorruptedError, match="time"):
        env.validate_state(torch.stack([good, bad]))
    assert_bitwise_equal(env.get_state(), good, "state after validating a batch")
