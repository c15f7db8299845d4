"""Bad input gets an error that names the problem, and leaves the env exactly as it was.

After every error the env's state is compared bitwise with its state before, and the
env then steps alongside a twin that never saw the error (built and driven identically,
no restore involved): outputs and final state must match.
"""

from __future__ import annotations

import re

import pytest
import torch
from env_helpers import (
    assert_bitwise_equal,
    faithful_copy,
    restore,
)
from error_helpers import (
    SCENARIO,
    assert_untouched,
    expect_restore_error,
    warmed_up,
)
from tensordict import NonTensorData

from torchrl_grpo.envs import (
    HighwayEnv,
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    StateMismatchError,
    UnknownFieldError,
)


def test_error_hierarchy():
    for error in (StateMismatchError, StateCorruptedError, StateCapacityError, UnknownFieldError):
        assert issubclass(error, SnapshotError)
    assert issubclass(SnapshotError, ValueError)


# ---------------------------------------------------------------- another scenario / config
@pytest.mark.parametrize(
    "source",
    [
        pytest.param((SCENARIO, {"lanes_count": 4}), id="lanes_count"),
        pytest.param((SCENARIO, {"duration": 50}), id="duration"),
        pytest.param(("highway-v0", {}), id="highway-v0"),
    ],
)
def test_state_from_another_config_is_a_mismatch(source):
    scenario, config = source
    pad = {"max_vehicles": 60}  # same shapes: only the fingerprint tells them apart
    foreign = HighwayEnv(scenario, config=config, seed=0, **pad).get_state()
    env, twin = warmed_up(**pad), warmed_up(**pad)
    expect_restore_error(env, twin, foreign, StateMismatchError, "another scenario or config")


@pytest.mark.parametrize("source", ["merge-v0", "intersection-v0", "parking-v0"])
def test_state_from_another_scenario_is_refused(source, env_and_twin):
    foreign = HighwayEnv(source, seed=0).get_state()
    expect_restore_error(*env_and_twin, foreign, SnapshotError, ".")


def test_state_from_another_scenario_is_a_mismatch(env_and_twin):
    foreign = HighwayEnv("merge-v0", seed=0).get_state()
    expect_restore_error(*env_and_twin, foreign, StateMismatchError, "another scenario")


def test_state_from_another_padding_is_refused(env_and_twin):
    foreign = HighwayEnv(SCENARIO, seed=0, max_vehicles=40).get_state()
    expect_restore_error(*env_and_twin, foreign, SnapshotError, "layout")


def test_state_from_another_padding_is_a_mismatch(env_and_twin):
    foreign = HighwayEnv(SCENARIO, seed=0, max_vehicles=40).get_state()
    expect_restore_error(*env_and_twin, foreign, StateMismatchError, "layout")


def test_cartpole_state_into_highway_is_refused(env_and_twin):
    from torchrl_grpo.envs import SnapshotEnv

    foreign = SnapshotEnv("CartPole-v1", seed=0).get_state()
    expect_restore_error(*env_and_twin, foreign, SnapshotError, ".")


# ---------------------------------------------------------------- corrupted / truncated
def _leaves(td, dtype=None):
    return [k for k, v in td.items(True, True) if dtype is None or v.dtype == dtype]


@pytest.mark.parametrize("part", ["sim", "output"])
def test_truncated_state_names_the_missing_entry(part, env_and_twin):
    env, twin = env_and_twin
    state = env.get_state()
    for key in _leaves(state[part])[:: max(1, len(_leaves(state[part])) // 4)]:
        broken = faithful_copy(state)
        del broken[part][key]
        leaf = key[-1] if isinstance(key, tuple) else key
        with pytest.raises(StateCorruptedError, match=f"truncated.*{re.escape(leaf)}"):
            restore(env, broken)
    # The whole simulator part missing (the message could name it: it says "got NoneType").
    expect_restore_error(env, twin, state.exclude("sim"), StateCorruptedError, "sim|TensorDict")


def test_wrong_dtype_and_shape_are_named(env_and_twin):
    env, twin = env_and_twin
    state = env.get_state()
    broken = faithful_copy(state)
    broken["sim", "env", "time"] = broken["sim", "env", "time"].view(torch.float64).float()
    with pytest.raises(StateCorruptedError, match="dtype"):
        restore(env, broken)
    shaped = [k for k in _leaves(state["sim"]) if state["sim"][k].ndim >= 1]
    broken = faithful_copy(state)
    broken["sim", *_as_tuple(shaped[0])] = broken["sim", *_as_tuple(shaped[0])][:-1]
    with pytest.raises(StateCorruptedError, match="shape"):
        restore(env, broken)
    broken = faithful_copy(state)
    broken["output", "observation"] = broken["output", "observation"][:2]
    expect_restore_error(env, twin, broken, StateCorruptedError, "observation.*shape")


# Entries of a highway state that hold float64 values as int64 bit patterns.
FLOAT_ENTRIES = (
    ("env", "time"),
    ("env", "class_params"),
    ("env", "features_range"),
    ("entities", "f64"),
)


def _as_tuple(key):
    return key if isinstance(key, tuple) else (key,)


@pytest.mark.parametrize(
    "key,value,match",
    [
        (("env", "time"), float("nan"), "time"),
        (("env", "time"), float("inf"), "time"),
        (("env", "rng"), -1, "random"),
    ],
)
def test_invalid_values_are_refused(key, value, match, env_and_twin):
    env, twin = env_and_twin
    broken = faithful_copy(env.get_state())
    entry = broken["sim", *key]
    if key in FLOAT_ENTRIES:
        entry.view(torch.float64).fill_(value)  # floats are stored as int64 bit patterns
    else:
        entry.fill_(value)
    expect_restore_error(env, twin, broken, StateCorruptedError, match)


def test_all_floats_nan_is_refused(env_and_twin):
    env, twin = env_and_twin
    broken = faithful_copy(env.get_state())
    for key in FLOAT_ENTRIES:
        broken["sim", *key].view(torch.float64).fill_(float("nan"))
    expect_restore_error(env, twin, broken, StateCorruptedError, ".")


def test_extra_and_non_tensor_entries(env_and_twin):
    env, twin = env_and_twin
    state = env.get_state()
    extra = faithful_copy(state)
    extra["sim", "env", "surprise"] = torch.zeros(())
    with pytest.raises(StateMismatchError, match="surprise"):
        restore(env, extra)
    non_tensor = faithful_copy(state)
    non_tensor["sim", "env", "time"] = NonTensorData("12.0")
    expect_restore_error(env, twin, non_tensor, StateCorruptedError, "time")


def test_batched_state_into_unbatched_env(env_and_twin):
    env, twin = env_and_twin
    state = env.get_state()
    expect_restore_error(env, twin, state.unsqueeze(0), StateCorruptedError, "batch")


def _corruptions(value):
    if value.dtype == torch.bool:
        return [~value]
    if value.dtype.is_floating_point:
        return [torch.full_like(value, float("nan")), torch.full_like(value, 1e300)]
    info = torch.iinfo(value.dtype)
    return [torch.full_like(value, info.max), torch.full_like(value, -7), value + 1]


@pytest.mark.parametrize("scenario", ["highway-fast-v0", "intersection-v0", "parking-v0"])
def test_fuzzed_states_fail_only_with_snapshot_errors(scenario):
    """Corrupt one entry at a time: restoring either raises a SnapshotError that leaves the
    env untouched (never an IndexError / KeyError / half-written env), or works, and then
    restoring the clean state is exact again."""
    env, twin = warmed_up(scenario, max_vehicles=40), warmed_up(scenario, max_vehicles=40)
    state = env.get_state()
    refused = 0
    for key in _leaves(state["sim"]):
        if key == ("env", "road_steps"):
            continue  # test_restore_removes_a_road_step_counter_the_state_does_not_have
        for bad in _corruptions(state["sim"][key]):
            broken = faithful_copy(state)
            broken["sim", *_as_tuple(key)] = bad
            try:
                env.validate_state(broken)
                valid = True
            except SnapshotError:
                valid = False
            try:
                restore(env, broken)
                assert valid, f"validate_state refused corrupted {key}, restore accepted it"
            except SnapshotError:
                refused += 1
                assert not valid, f"validate_state accepted corrupted {key}, restore refused it"
                assert_bitwise_equal(env.get_state(), state, f"after refusing corrupted {key}")
            except Exception as err:  # noqa: BLE001 - the point of the test
                pytest.fail(f"corrupting {key} raised {type(err).__name__}: {err}")
            else:
                restore(env, state)
                assert_bitwise_equal(env.get_state(), state, f"clean restore after {key}")
    assert refused >= 10
    assert_untouched(env, state, twin)


def test_corrupted_presence_flags_raise_a_snapshot_error():
    env = warmed_up("lane-keeping-v0")
    state = env.get_state()
    broken = faithful_copy(state)
    for key in _leaves(broken["sim", "entities"], torch.bool):
        broken["sim", "entities", *_as_tuple(key)] = ~broken["sim", "entities", *_as_tuple(key)]
    with pytest.raises(StateCorruptedError):
        restore(env, broken)
    assert_bitwise_equal(env.get_state(), state, "after the refusal")


def test_restore_removes_a_road_step_counter_the_state_does_not_have(env_and_twin):
    env, twin = env_and_twin
    state = env.get_state()
    odd = faithful_copy(state)
    odd["sim", "env", "road_steps"] = torch.full_like(odd["sim", "env", "road_steps"], 3)
    try:
        restore(env, odd)
    except SnapshotError:
        pass  # refusing it is fine too
    restore(env, state)
    assert_untouched(env, state, twin)
