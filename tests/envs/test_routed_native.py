"""merge-v0's and roundabout-v0's C++ substeps (``TensorHighwayEnv(scenario, native=True)``).

Two references: highway-env itself, through the parity ladder's rungs a to c on worlds
recorded from highway-env runs (vehicles on the sines, the ramp and the ring, handing
over between roads, merge's obstacle; intersection-v0's C++ frames too, whose other
tests are test_intersection_native.py), and the tensor step, which the C++ step follows
expression by expression: in float64 they agree to rounding after a step, with the same
lanes, targets, route heads and crashes; in float32 to an ulp or two in all but the
ill-conditioned worlds (a nearly stopped ego steering by its clip).
"""

from __future__ import annotations

import logging

import pytest
import torch
from env_helpers import replayed_twice, stepped_states
from omegaconf import OmegaConf
from parity_helpers import recording_policies
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import TensorHighwayEnv, tensor_params
from torchrl_grpo.envs.highway.parity import one_step, record_worlds, same_world, whole_episodes
from torchrl_grpo.envs.highway.parity_policies import ladder_policies
from torchrl_grpo.envs.highway.step_modes import native_mode
from torchrl_grpo.sim.roundabout import roundabout_step
from torchrl_grpo.sim.routed_native import routed_step
from torchrl_grpo.training.env_builder import steps_natively

SCENARIO = "roundabout-v0"
SCENARIOS = ("merge-v0", "roundabout-v0")


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_specs_and_rollout(scenario):
    env = TensorHighwayEnv(scenario, num_envs=6, seed=1, native=True)
    assert env.step_mode == "native"
    check_env_specs(env)
    assert env.rollout(4, break_when_any_done=False)["next", "observation"].shape == (6, 4, 5, 5)


def _one_step_pairs(dtype, scenario=SCENARIO):
    """(state, C++ state, tensor state) after one step from each of a few states."""
    states = stepped_states(scenario, dtype, steps=12)
    batch = states[0].shape[0]
    action = TensorDict(action=torch.arange(batch) % 5, batch_size=[batch])
    envs = [
        TensorHighwayEnv(scenario, num_envs=batch, dtype=dtype, native=flag)
        for flag in (True, False)
    ]
    for state in states[1::3]:
        outs = []
        for env in envs:
            env.reset(TensorDict(state=state, batch_size=[batch]), set_state=True)
            env.step(action.clone())
            outs.append(env.get_state())
        yield state, outs[0], outs[1]


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_one_step_agrees_with_the_tensor_step_in_float64(scenario):
    # An ulp of a sine or an arcsine (libm's against torch's) grows through a step's
    # substeps; most through the steering of a nearly stopped ego, whose arcsine sits by
    # its clip (1e-8 there; 1e-14 elsewhere). Every discrete field is the same.
    crashed = moved_on = 0
    for before, native, tensor in _one_step_pairs(torch.float64, scenario):
        torch.testing.assert_close(native, tensor, rtol=0, atol=1e-6)
        crashed += int(native["vehicles", "crashed"].sum())
        road = tensor_params(scenario).road.road
        lanes = (before["vehicles", "lane"], native["vehicles", "lane"])
        moved_on += int((torch.tensor(road)[lanes[0]] != torch.tensor(road)[lanes[1]]).sum())
    assert crashed > 0 and moved_on > 0  # the comparison covered crashes and hand-overs


def test_one_step_in_float32_agrees_in_all_but_ill_conditioned_worlds():
    # float32 rounds the same arcsine by its clip to either side: a nearly stopped ego
    # may steer to the opposite clip. Every other world agrees to an ulp or two.
    worlds = agreeing = 0
    for _, native, tensor in _one_step_pairs(torch.float32):
        v, w = native["vehicles"], tensor["vehicles"]
        close = torch.ones(v.shape[0], dtype=torch.bool)
        for key in ("x", "y", "heading", "speed", "steering"):
            close &= ((v[key] - w[key]).abs() <= 1e-4 + 1e-6 * w[key].abs()).all(-1)
        for key in ("lane", "target_lane", "crashed"):
            close &= (v[key] == w[key]).all(-1)
        worlds, agreeing = worlds + close.numel(), agreeing + int(close.sum())
    assert agreeing >= 0.95 * worlds, (agreeing, worlds)


@pytest.mark.parametrize(
    ("scenario", "dtype"), [("roundabout-v0", torch.float32), ("merge-v0", torch.float64)]
)
def test_a_restore_replays_the_same_bits(scenario, dtype):
    env = TensorHighwayEnv(scenario, num_envs=12, seed=3, dtype=dtype, native=True)
    env.reset()
    plays = replayed_twice(env, 14)  # 14 steps: episodes end and rows reset
    torch.testing.assert_close(plays[0], plays[1], rtol=0, atol=0)


@pytest.fixture(scope="module", params=(*SCENARIOS, "intersection-v0"))
def recorded(request):
    scenario = request.param
    env = TensorHighwayEnv(scenario, num_envs=15, dtype=torch.float64, native=True)
    policies = recording_policies(env.config, scenario)
    states, kinds = record_worlds(scenario, policies, 15, seed=0)
    # Curves and hand-overs, and lane changes (intersection-v0: cars yielding).
    turn = "yielding" if scenario == "intersection-v0" else "changing"
    assert kinds["curved"] > 0 and kinds["hand_over"] > 0 and kinds[turn] > 0, kinds
    return env, states


def test_ladder_a_b_against_highway_env(recorded):
    env, states = recorded
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["reward"] <= 1e-9 and worst["flags"] == 0
    report = one_step(env, states)
    assert report.pairs == 15 * env.action_spec.space.n and report.agreement >= 0.995
    assert not report.misses


def test_ladder_c_whole_episodes(recorded):
    env, states = recorded
    small = TensorHighwayEnv(env.scenario, num_envs=3, dtype=torch.float64, native=True)
    drive = ladder_policies(env.scenario, env.config)["drive"]
    horizons = whole_episodes(small, states[::5][:3], drive)
    assert bool((horizons == -1).all()), horizons


def test_threads_split_worlds_without_changing_bits():
    params = tensor_params(SCENARIO)
    world = TensorHighwayEnv(SCENARIO, num_envs=70, seed=4)._world
    action = torch.arange(70) % 5
    one, _ = routed_step(world, action, params, threads=1)
    three, _ = routed_step(world, action, params, threads=3)
    for a, b in zip(one.vehicles, three.vehicles, strict=True):
        assert torch.equal(a, b)
    assert torch.equal(one.route_head, three.route_head)


def test_the_input_world_is_left_as_it_was_and_a_float64_step_matches():
    params = tensor_params(SCENARIO)
    world = TensorHighwayEnv(SCENARIO, num_envs=4, seed=4, dtype=torch.float64)._world
    before = [t.clone() for t in (*world.vehicles, world.route_head)]
    native, out = routed_step(world, torch.full((4,), 3), params)
    after = [*world.vehicles, world.route_head]
    assert all(torch.equal(a, b) for a, b in zip(before, after, strict=True))
    tensor, ref = roundabout_step(world, torch.full((4,), 3), params)
    torch.testing.assert_close(native.vehicles.x, tensor.vehicles.x, rtol=0, atol=1e-11)
    torch.testing.assert_close(out["reward"], ref["reward"], rtol=0, atol=1e-12)


def test_errors_name_the_problem_and_the_env_steps_on():
    params = tensor_params(SCENARIO)
    merge_world = TensorHighwayEnv("merge-v0", num_envs=2, seed=0)._world
    with pytest.raises(ValueError, match="RoundaboutParams needs worlds with routes"):
        routed_step(merge_world, torch.zeros(2, dtype=torch.int64), params)
    with pytest.raises(ValueError, match="on the CPU"):
        native_mode(SCENARIO, params, torch.device("cuda"))
    many = {"action": {"type": "DiscreteMetaAction", "target_speeds": list(range(20))}}
    with pytest.raises(ValueError, match="1 to 16 target speeds, got 20"):
        TensorHighwayEnv(SCENARIO, many, num_envs=2, native=True)
    with pytest.raises(ValueError, match="not 'parking-v0'"):
        native_mode("parking-v0", params, torch.device("cpu"))
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0, native=True)
    assert env.rollout(2)["next", "reward"].shape == (2, 2, 1)


def test_training_steps_merge_and_the_roundabout_in_cpp_by_default():
    cfg = OmegaConf.create({"backend": "auto", "scenario": SCENARIO, "config": {}})
    assert steps_natively(cfg) and steps_natively(OmegaConf.merge(cfg, {"scenario": "merge-v0"}))
    assert not steps_natively(OmegaConf.merge(cfg, {"backend": "tensor"}))


@pytest.mark.parametrize("scenario", ["highway-fast-v0", SCENARIO])
def test_a_config_the_cpp_step_cannot_hold_steps_with_tensors_under_auto(scenario, caplog):
    many = {"action": {"type": "DiscreteMetaAction", "target_speeds": list(range(20))}}
    cfg = OmegaConf.create({"backend": "auto", "scenario": scenario, "config": many})
    with caplog.at_level(logging.INFO, logger="torchrl_grpo.training.env_builder"):
        assert not steps_natively(cfg)
    assert (
        "cannot hold this config (the C++ step takes 1 to 16 target speeds, got 20)" in caplog.text
    )
    with pytest.raises(ValueError, match="1 to 16 target speeds, got 20"):
        TensorHighwayEnv(scenario, many, num_envs=2, native=True)  # refused when built
