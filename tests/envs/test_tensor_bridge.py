"""The bridge: HighwayEnv states <-> tensor states, bit for bit, and highway-env renders them."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv, StateMismatchError, TensorHighwayEnv, state_differences

CONFIGS = [
    ("highway-fast-v0", {}),
    ("highway-v0", {"vehicles_count": 12}),
    (
        "highway-fast-v0",
        {
            "lanes_count": 4,
            "action": {"type": "DiscreteMetaAction", "target_speeds": [18, 24, 30, 36]},
        },
    ),
]


def visited_states(scenario, config, episodes=2, steps=12):
    """States of highway-env episodes under random actions, the final (crashed) ones included."""
    env = HighwayEnv(scenario, config, seed=0)
    rng = np.random.default_rng(0)
    states = []
    for _ in range(episodes):
        td = env.reset()
        for _ in range(steps):
            states.append(env.get_state())
            td = env.step(TensorDict(action=torch.tensor(int(rng.integers(5)))))
            if bool(td["next", "done"]):
                states.append(env.get_state())
                break
    return torch.stack(states)


@pytest.mark.parametrize(("scenario", "config"), CONFIGS)
def test_round_trip_from_highway_env_is_bitwise(scenario, config):
    states = visited_states(scenario, config)
    env = TensorHighwayEnv(scenario, config, num_envs=1, dtype=torch.float64)
    back = env.state_to_highway(env.state_from_highway(states))
    for i in range(states.shape[0]):
        assert state_differences(states[i], back[i]) == [], i


def test_tensor_worlds_continue_and_render_in_highway_env():
    env = TensorHighwayEnv(num_envs=2, seed=0, dtype=torch.float64)
    env.reset()
    for _ in range(3):
        env.step(TensorDict(action=torch.tensor([3, 0]), batch_size=[2]))
    tensor_state = env.get_state()
    highway_states = env.state_to_highway(tensor_state)
    hw = HighwayEnv("highway-fast-v0", render_mode="rgb_array")
    td = hw.set_state(highway_states[1])
    assert torch.allclose(
        td["ego_position"].double(),
        tensor_state["vehicles", "x"][1, :1]
        .new_tensor([tensor_state["vehicles", "x"][1, 0], tensor_state["vehicles", "y"][1, 0]])
        .float()
        .double(),
        atol=1e-4,
    )
    hw.step(TensorDict(action=torch.tensor(1)))  # highway-env continues the tensor world
    frame = hw.render()
    assert frame.ndim == 3 and frame.mean() > 0  # not blank
    frames = env.render_frames(tensor_state)
    assert len(frames) == 2 and frames[0].shape == frame.shape and frames[0].std() > 0


def test_states_of_another_config_are_refused():
    states = visited_states("highway-fast-v0", {"lanes_count": 4}, episodes=1, steps=2)
    env = TensorHighwayEnv(num_envs=1)
    with pytest.raises(StateMismatchError):
        env.state_from_highway(states)


def test_float32_worlds_import_rounded():
    states = visited_states("highway-fast-v0", {}, episodes=1, steps=3)
    env = TensorHighwayEnv(num_envs=1)
    tensor = env.state_from_highway(states)
    assert tensor["vehicles", "x"].dtype == torch.float32 and tensor["time"].dtype == torch.float64
    env64 = TensorHighwayEnv(num_envs=1, dtype=torch.float64)
    exact = env64.state_from_highway(states)
    assert torch.allclose(tensor["vehicles", "x"].double(), exact["vehicles", "x"], rtol=1e-7)
