"""A tensor state's floats are held to the magnitude bound of HighwayEnv's codec."""

from __future__ import annotations

import re

import pytest
import torch
from env_helpers import assert_bitwise_equal
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv, SnapshotError, StateCorruptedError, TensorHighwayEnv
from torchrl_grpo.envs.highway.schema import MAX_MAGNITUDE
from torchrl_grpo.sim.state import FLOAT_FIELDS

# The first float32 beyond the bound (1e9 itself is a float32).
JUST_BEYOND = float(torch.nextafter(torch.tensor(MAX_MAGNITUDE), torch.tensor(float("inf"))))


@pytest.fixture(scope="module")
def envs():
    env = TensorHighwayEnv(num_envs=3, seed=0)
    env.reset()
    return env, HighwayEnv("highway-fast-v0", seed=0)


def edited(state, key, value):
    out = state.clone()
    out.get(key)[1, 2] = value  # row 1, vehicle 2
    return out


def verdict(check, state) -> str:
    try:
        check(state)
    except SnapshotError:
        return "refused"
    return "admitted"


@pytest.mark.parametrize("field", ["x", "y", "heading", "speed", "target_speed"])
@pytest.mark.parametrize("value", [MAX_MAGNITUDE, -1e6, -JUST_BEYOND, 1e30, -2e9])
def test_the_bound_is_highway_envs_own(envs, field, value):
    """The tensor env admits what HighwayEnv's codec admits, on the same world exported."""
    env, highway = envs
    state = edited(env.get_state(), ("vehicles", field), value)
    exported = env.state_to_highway(state[1:2])[0]
    assert verdict(env.validate_state, state) == verdict(highway.validate_state, exported)
    expected = "admitted" if abs(value) <= MAX_MAGNITUDE else "refused"
    assert verdict(env.validate_state, state) == expected


@pytest.mark.parametrize("field", FLOAT_FIELDS)
def test_each_float_field_beyond_the_bound_is_refused_by_name(field):
    env, twin = TensorHighwayEnv(num_envs=3, seed=0), TensorHighwayEnv(num_envs=3, seed=0)
    env.reset(), twin.reset()
    good = env.get_state()
    bad = edited(good, ("vehicles", field), 1e30)
    bad.get(("vehicles", field))[2, 0] = -JUST_BEYOND
    stored = bad.get(("vehicles", field))
    values = [stored[1, 2].item(), stored[2, 0].item()]
    message = f"vehicles.{field}: not finite, or beyond 1e+09 in rows [1, 2] (values {values})"
    with pytest.raises(StateCorruptedError, match=re.escape(message)):
        env.reset(TensorDict(state=bad, batch_size=[3]), set_state=True)
    assert_bitwise_equal(env.get_state(), good, "state after the refusal")
    action = TensorDict(action=torch.tensor([0, 1, 3]), batch_size=[3])
    assert_bitwise_equal(env.step(action.clone()), twin.step(action.clone()), "step after")


def test_the_clock_beyond_the_bound_is_refused_by_name(envs):
    env, _ = envs
    state = env.get_state()
    state["time"][0] = 2e9
    with pytest.raises(StateCorruptedError, match=re.escape("time: negative, not finite, or ")):
        env.validate_state(state)
    with pytest.raises(StateCorruptedError, match=re.escape("rows [0] (values [2000000000.0])")):
        env.validate_state(state)


def test_the_bound_is_not_checked_with_check_states_off():
    env = TensorHighwayEnv(num_envs=2, seed=0, check_states=False)
    env.reset()
    env.validate_state(edited(env.get_state(), ("vehicles", "x"), 1e30))  # admitted
