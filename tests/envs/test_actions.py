"""Actions outside an env's action spec are refused by name, and the env steps on unchanged."""

from __future__ import annotations

import functools

import pytest
import torch
from env_helpers import assert_bitwise_equal
from error_helpers import assert_untouched, warmed_up
from tensordict import TensorDict

from torchrl_grpo.envs import (
    HighwayEnv,
    InvalidActionError,
    SnapshotEnv,
    SnapshotParallelEnv,
    SnapshotSerialEnv,
    TensorHighwayEnv,
)


def tensor_env(**kwargs) -> TensorHighwayEnv:
    env = TensorHighwayEnv(num_envs=4, seed=0, **kwargs)
    env.reset()
    return env


def step(env, action: torch.Tensor) -> TensorDict:
    return env.step(TensorDict(action=action, batch_size=env.batch_size))["next"]


def assert_steps_like_twin(env, twin, actions: list[torch.Tensor]) -> None:
    """Every output and the final state equal, bit for bit, the twin's (which saw no bad call)."""
    for action in actions:
        assert_bitwise_equal(step(env, action.clone()), step(twin, action.clone()), "step")
    assert_bitwise_equal(env.get_state(), twin.get_state(), "state")


# ------------------------------------------------------------------ TensorHighwayEnv
@pytest.mark.parametrize(
    ("action", "match"),
    [
        # 7, -1 and 5 are outside Categorical(5); the message lists rows and values.
        ([1, 7, 2, 1], r"rows \[1\]: values \[7\]"),
        ([-1, 1, 1, 5], r"rows \[0, 3\]: values \[-1, 5\]"),
        ([1.5, 1.0, 1.0, 1.0], r"dtype torch.float32 \(\[1.5, 1.0, 1.0, 1.0\]\)"),
        ([[1], [1], [1], [1]], r"shape \(4, 1\)"),
    ],
)
def test_tensor_env_refuses_actions_outside_its_spec(action, match):
    env, twin = tensor_env(), tensor_env()
    before = env.get_state()
    with pytest.raises(InvalidActionError, match=match) as err:
        step(env, torch.tensor(action))
    assert isinstance(err.value, ValueError)
    text = str(err.value)
    assert "TensorHighwayEnv('highway-fast-v0', num_envs=4)" in text
    assert "Categorical(n=5: integers 0..4, shape=(4,), dtype=torch.int64)" in text
    assert_bitwise_equal(env.get_state(), before, "state after the refusal")
    assert env.world_steps == twin.world_steps
    g = torch.Generator().manual_seed(3)
    assert_steps_like_twin(env, twin, [torch.randint(0, 5, (4,), generator=g) for _ in range(4)])


@pytest.mark.parametrize(
    ("action", "match"),
    [
        ([[0, 1, 0, 0, 0], [1, 1, 0, 0, 0]], r"rows \[1\]: values \[\[1, 1, 0, 0, 0\]\]"),
        ([[0, 0, 0, 0, 0], [0, 1, 0, 0, 0]], r"rows \[0\]"),
        ([[0, 2, -1, 0, 0], [0, 1, 0, 0, 0]], r"rows \[0\]"),  # sums to 1, is no one-hot
        ([[0.0, 1.0, 0.0, 0.0, 0.0]] * 2, r"dtype torch.float32"),
        ([0, 1], r"shape \(2,\)"),
    ],
)
def test_one_hot_tensor_env_refuses_what_is_not_one_hot(action, match):
    env = TensorHighwayEnv(num_envs=2, seed=0, categorical_action_encoding=False)
    twin = TensorHighwayEnv(num_envs=2, seed=0, categorical_action_encoding=False)
    env.reset(), twin.reset()
    with pytest.raises(InvalidActionError, match=match) as err:
        step(env, torch.tensor(action))
    assert "OneHot(n=5" in str(err.value)
    idle = torch.nn.functional.one_hot(torch.tensor([1, 3]), 5)
    assert_steps_like_twin(env, twin, [idle, idle.flip(0)])


def test_rows_outside_a_partial_step_are_not_checked():
    env, twin = tensor_env(), tensor_env()
    mask = torch.tensor([True, False, True, False])
    # Row 1 does not step: its value is never read, as TorchRL's partial steps promise.
    data = TensorDict(action=torch.tensor([1, 9, 2, 1]), _step=mask, batch_size=[4])
    env.step(data)
    twin.step(TensorDict(action=torch.tensor([1, 1, 2, 1]), _step=mask, batch_size=[4]))
    assert_bitwise_equal(env.get_state(), twin.get_state(), "state")
    with pytest.raises(InvalidActionError, match=r"rows \[2\]: values \[9\]"):
        env.step(TensorDict(action=torch.tensor([1, 9, 9, 1]), _step=mask, batch_size=[4]))


def test_the_action_check_can_be_turned_off():
    env = tensor_env(check_actions=False)
    step(env, torch.tensor([1, 7, 1, 1]))  # not refused: the switch is the user's promise


def test_rollouts_with_valid_actions_are_unchanged_by_the_check():
    env, twin = tensor_env(), tensor_env(check_actions=False)
    g = torch.Generator().manual_seed(0)
    actions = [torch.randint(0, 5, (4,), generator=g) for _ in range(6)]
    assert_steps_like_twin(env, twin, actions)


# ------------------------------------------------------------------ HighwayEnv / SnapshotEnv
@pytest.mark.parametrize(
    ("action", "match"),
    [
        (torch.tensor(7), r"action 7 is outside the action spec Categorical\(n=5"),
        (torch.tensor(-1), r"action -1 is outside"),
        (torch.tensor(5), r"action 5 is outside"),
        (torch.tensor(1.5), r"dtype torch.float32 \(1.5\)"),
        (torch.tensor([1]), r"shape \(1,\)"),
    ],
)
def test_highway_env_refuses_actions_outside_its_spec(action, match):
    env, twin = warmed_up(), warmed_up()
    before = env.get_state()
    with pytest.raises(InvalidActionError, match=match) as err:
        env.step(TensorDict(action=action))
    assert str(err.value).startswith("HighwayEnv('highway-fast-v0'): ")
    assert_untouched(env, before, twin)


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (torch.tensor([2.0, 0.0]), r"action \[2.0, 0.0\] is outside .*BoundedContinuous"),
        (torch.tensor([0.0, float("nan")]), r"action \[0.0, nan\] is outside"),
        (torch.tensor([1, 0]), r"dtype torch.int64 .* takes floats"),
        (torch.zeros(3), r"shape \(3,\)"),
    ],
)
def test_continuous_actions_outside_the_bounds_are_refused(action, match):
    env, twin = warmed_up("parking-v0"), warmed_up("parking-v0")
    before = env.get_state()
    with pytest.raises(InvalidActionError, match=match) as err:
        env.step(TensorDict(action=action))
    assert "low=[-1.0, -1.0], high=[1.0, 1.0]" in str(err.value)
    assert_untouched(env, before, twin)


@pytest.mark.parametrize(
    ("categorical", "action", "match"),
    [
        (True, torch.tensor(2), r"SnapshotEnv\('CartPole-v1'\): action 2 is outside"),
        (True, torch.tensor(0.5), r"dtype torch.float32"),
        (False, torch.tensor([1, 1]), r"action \[1, 1\] is outside the action spec OneHot\(n=2"),
        (False, torch.tensor([2, -1]), r"action \[2, -1\] is outside"),
        (False, torch.tensor(1), r"shape \(\)"),
    ],
)
def test_codec_env_refuses_actions_outside_its_spec(categorical, action, match):
    make = functools.partial(
        SnapshotEnv, "CartPole-v1", seed=0, categorical_action_encoding=categorical
    )
    env, twin = make(), make()
    env.reset(), twin.reset()
    before = env.get_state()
    with pytest.raises(InvalidActionError, match=match):
        env.step(TensorDict(action=action))
    assert_bitwise_equal(env.get_state(), before, "state after the refusal")
    push = torch.tensor(1) if categorical else torch.tensor([0, 1])
    for _ in range(3):
        a, b = env.step(TensorDict(action=push)), twin.step(TensorDict(action=push))
        assert_bitwise_equal(a["next"], b["next"], "step")


def test_highway_env_action_check_can_be_turned_off():
    env = warmed_up(check_actions=False)
    with pytest.raises(KeyError):  # highway-env's own error, as before the check
        env.step(TensorDict(action=torch.tensor(7)))


# ------------------------------------------------------------------ batched envs
def _batched(cls, **kwargs):
    kw = {"mp_start_method": "fork"} if cls is SnapshotParallelEnv else {}
    env = cls(2, functools.partial(HighwayEnv, "highway-fast-v0", seed=0), **kw, **kwargs)
    env.reset()
    return env


@pytest.mark.parametrize(
    ("cls", "action", "match"),
    [
        (SnapshotSerialEnv, [1, 7], r"rows \[1\]: values \[7\]"),
        (SnapshotSerialEnv, [1.0, 1.5], r"dtype torch.float32 \(\[1.0, 1.5\]\)"),
        (SnapshotSerialEnv, [[1], [1]], r"shape \(2, 1\)"),
        (SnapshotParallelEnv, [1, 7], r"rows \[1\]: values \[7\]"),
    ],
)
def test_batched_envs_refuse_a_bad_action_before_any_worker_steps(cls, action, match):
    env, twin = _batched(cls), _batched(SnapshotSerialEnv)
    try:
        before = torch.stack(env.get_state())
        bad = TensorDict(action=torch.tensor(action), batch_size=[2])
        name = f"{cls.__name__} of 2 workers"
        with pytest.raises(InvalidActionError, match=rf"{name}: .*{match}"):
            env.step(bad.clone())
        with pytest.raises(InvalidActionError, match=match):
            env.step_and_maybe_reset(bad.clone())
        # Worker 0 did not step before worker 1 refused (a plain SerialEnv steps it).
        assert_bitwise_equal(torch.stack(env.get_state()), before, "workers' states")
        good = TensorDict(action=torch.tensor([1, 3]), batch_size=[2])
        a, b = env.step(good.clone())["next"], twin.step(good.clone())["next"]
        assert_bitwise_equal(a.exclude("state"), b.exclude("state"), "step")
    finally:
        env.close()
        twin.close()
