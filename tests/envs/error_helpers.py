"""Helpers of the bad-input tests: a warmed-up env, and the check an error left it as it was."""

from __future__ import annotations

import pytest
from env_helpers import (
    assert_bitwise_equal,
    assert_same_run,
    careful_actions,
    random_actions,
    restore,
    run,
)
from highway_env.vehicle.behavior import IDMVehicle
from tensordict import TensorDictBase

from torchrl_grpo.envs import HighwayEnv

SCENARIO = "highway-fast-v0"


class UnregisteredIDM(IDMVehicle):
    """A vehicle class the codec has never heard of."""


def warmed_up(scenario=SCENARIO, steps=2, **kwargs) -> HighwayEnv:
    env = HighwayEnv(scenario, seed=0, **kwargs)
    run(env, careful_actions(env, steps))
    return env


def assert_untouched(env, before, twin, steps: int = 6) -> None:
    """The env holds the state it had, and still steps exactly like its twin."""
    assert_bitwise_equal(env.get_state(), before, "state after the error")
    actions = random_actions(env, steps, seed=11)
    outputs, final = run(env, actions)
    ref_outputs, ref_final = run(twin, actions)
    assert_same_run(ref_outputs, outputs, "steps after the error")
    assert_bitwise_equal(final, ref_final, "state after stepping on")


def expect_restore_error(env, twin, state, error, match):
    before = env.get_state()
    if isinstance(state, TensorDictBase) and "sim" in state.keys() and not state.batch_dims:
        # validate_state runs the same checks in this process, without restoring.
        with pytest.raises(error, match=match):
            env.validate_state(state)
        assert_bitwise_equal(env.get_state(), before, "state after validate_state")
    with pytest.raises(error, match=match):
        restore(env, state)
    assert_untouched(env, before, twin)
