"""FastKinematicObservation against highway-env's own observe, bit for bit, step by step."""

from __future__ import annotations

import gymnasium as gym
import highway_env  # noqa: F401 - registers the scenarios
import numpy as np
import pytest
import torch
from highway_env.envs.common.observation import KinematicObservation
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.envs.highway.fast_observation import (
    FastKinematicObservation,
    use_fast_kinematics,
)

CASES = {
    "highway-fast": ("highway-fast-v0", {}),
    "merge": ("merge-v0", {}),
    # Given ranges, absolute coordinates, 15 vehicles, cos_h/sin_h, no intentions.
    "intersection": ("intersection-v0", {}),
    "roundabout": ("roundabout-v0", {}),
    "behind-unclipped-shuffled": (
        "highway-fast-v0",
        {"see_behind": True, "clip": False, "order": "shuffled", "vehicles_count": 8},
    ),
    "raw-offsets": (
        "merge-v0",
        {
            "normalize": False,
            "features": ["presence", "x", "heading", "long_off", "lat_off", "ang_off", "cos_d"],
            "observe_intentions": False,
        },
    ),
    # One observed vehicle: highway-env's slice close[-0:] keeps every close vehicle.
    "one-vehicle": ("highway-fast-v0", {"vehicles_count": 1}),
}


def _observe(observer, cls) -> tuple[np.ndarray, dict]:
    """``cls.observe`` from the simulator's generator state, and the state it leaves."""
    rng = observer.env.np_random
    start = rng.bit_generator.state
    obs = cls.observe(observer)
    end = rng.bit_generator.state
    rng.bit_generator.state = start
    return obs, end


@pytest.mark.parametrize("case", sorted(CASES))
def test_every_observation_is_highway_envs_bit_for_bit(case):
    scenario, extra = CASES[case]
    env = gym.make(scenario, disable_env_checker=True)
    config = {**env.unwrapped.config["observation"], **extra}
    env.unwrapped.configure({"observation": config})
    env.reset(seed=3)
    env.action_space.seed(3)
    compared = 0
    for step in range(60):
        observer = env.unwrapped.observation_type
        slow, slow_rng = _observe(observer, KinematicObservation)
        fast, fast_rng = _observe(observer, FastKinematicObservation)
        assert fast.dtype == slow.dtype and fast.shape == slow.shape, case
        assert fast.tobytes() == slow.tobytes(), (case, step)
        assert fast_rng == slow_rng  # a shuffled order draws the same numbers
        compared += 1
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset(seed=100 + step)
    assert compared == 60


def test_a_feature_no_vehicle_has_is_a_key_error_as_in_highway_env():
    env = gym.make("highway-fast-v0", disable_env_checker=True)
    env.reset(seed=0)
    observer = env.unwrapped.observation_type
    observer.features = ["presence", "altitude"]
    with pytest.raises(KeyError):
        KinematicObservation.observe(observer)
    with pytest.raises(KeyError, match="altitude"):
        FastKinematicObservation.observe(observer)


def test_only_a_plain_kinematics_observation_is_swapped():
    env = gym.make("racetrack-v0", disable_env_checker=True)
    env.reset(seed=0)
    assert use_fast_kinematics(env.unwrapped) is False
    assert type(env.unwrapped.observation_type).__name__ == "OccupancyGridObservation"

    class Custom(KinematicObservation):
        pass

    env = gym.make("highway-fast-v0", disable_env_checker=True)
    env.reset(seed=0)
    env.unwrapped.observation_type.__class__ = Custom
    assert use_fast_kinematics(env.unwrapped) is False


@pytest.mark.parametrize("scenario", ["highway-fast-v0", "merge-v0"])
def test_highway_env_gives_the_same_outputs_and_states_with_and_without_it(scenario):
    fast, slow = (HighwayEnv(scenario, seed=5, fast_observation=f) for f in (True, False))
    actions = torch.randint(5, (45,), generator=torch.Generator().manual_seed(0))
    for env in (fast, slow):
        env.reset()
    for t, action in enumerate(actions):
        a, b = (env.step(TensorDict(action=action))["next"] for env in (fast, slow))
        assert (a == b).all(), t
        if bool(a["done"]):
            a, b = fast.reset(), slow.reset()  # the observation object is rebuilt
            assert (a == b).all(), t
    assert type(fast.gym_env.unwrapped.observation_type) is FastKinematicObservation
    assert type(slow.gym_env.unwrapped.observation_type) is KinematicObservation
    assert (fast.get_state() == slow.get_state()).all()
