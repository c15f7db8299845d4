"""The C++ step (``TensorHighwayEnv(native=True)``) against highway-env and the tensor step.

The reference is highway-env itself: the parity ladder's rungs a to d on worlds recorded
from highway-env runs, as tests/envs/test_tensor_parity.py runs them for the tensor
step. Against the tensor step, float64 agrees to rounding after one step; float32
differs where libm and torch round a sine or a power differently, so the C++ step is
held to its own bits on replays.
"""

import json
from pathlib import Path

import pytest
import torch
from env_helpers import replayed_twice, stepped_states
from parity_helpers import recording_policies, reference_policies
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import TensorHighwayEnv, tensor_params
from torchrl_grpo.envs.highway.parity import one_step, record_worlds, same_world, whole_episodes
from torchrl_grpo.envs.highway.parity_resets import fresh_resets
from torchrl_grpo.envs.highway.step_modes import native_mode
from torchrl_grpo.sim import native
from torchrl_grpo.sim.native import NativeBuildError, native_step

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "highway_reference"


@pytest.fixture(scope="module")
def fast_worlds():
    env = TensorHighwayEnv("highway-fast-v0", num_envs=40, dtype=torch.float64, native=True)
    states, kinds = record_worlds("highway-fast-v0", recording_policies(env.config), 40, seed=0)
    assert kinds["changing"] > 0 and kinds["near_miss"] > 0 and kinds["crashed"] > 0
    return env, states


def test_specs_and_rollout():
    env = TensorHighwayEnv(num_envs=6, seed=1, native=True)
    check_env_specs(env)
    assert env.rollout(4, break_when_any_done=False)["next", "observation"].shape == (6, 4, 5, 5)


def test_ladder_a_b_c_on_highway_fast(fast_worlds):
    env, states = fast_worlds
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["reward"] <= 1e-9 and worst["flags"] == 0
    report = one_step(env, states)
    assert report.pairs == 200 and report.agreement >= 0.995, report.misses
    small = TensorHighwayEnv("highway-fast-v0", num_envs=5, dtype=torch.float64, native=True)
    horizons = whole_episodes(small, states[::8][:5], recording_policies(env.config)[0])
    assert bool((horizons == -1).all()), horizons


def test_ladder_d_fresh_resets():
    reference = json.loads((REFERENCE / "highway-fast-v0.json").read_text())
    config = TensorHighwayEnv("highway-fast-v0", num_envs=1).config
    policies = reference_policies(config)
    table = fresh_resets("highway-fast-v0", reference, policies, episodes=300, native=True)
    assert all(row["p"] >= 0.01 / len(table) for row in table), table


@pytest.mark.slow  # 9 s; the default suite holds highway-v0 to the tensor step (below)
def test_ladder_a_b_on_highway_v0_all_pairs_collisions():
    env = TensorHighwayEnv("highway-v0", num_envs=5, dtype=torch.float64, native=True)
    assert env.params.traffic.others_check_collisions
    states, _ = record_worlds("highway-v0", recording_policies(env.config), 5, seed=0)
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["flags"] == 0
    assert one_step(env, states).agreement >= 0.995


@pytest.mark.parametrize("scenario", ["highway-fast-v0", "highway-v0"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_step_agrees_with_the_tensor_step(dtype, scenario):
    # float32: an ulp or two (positions reach 1 km on highway-v0: an ulp is 1.2e-4 there).
    rtol, atol = {torch.float32: (1e-6, 1e-4), torch.float64: (0, 1e-11)}[dtype]
    # highway-v0's tensor step is 3 times as long (15 substeps, 51 vehicles): fewer steps.
    states = stepped_states(scenario, dtype, steps=25 if scenario == "highway-fast-v0" else 10)
    batch = states[0].shape[0]
    action = TensorDict(action=torch.arange(batch) % 5, batch_size=[batch])
    envs = [
        TensorHighwayEnv(scenario, num_envs=batch, dtype=dtype, native=flag)
        for flag in (True, False)
    ]
    for state in states[::6]:
        outs = []
        for env in envs:
            env.reset(TensorDict(state=state, batch_size=[batch]), set_state=True)
            outs.append((env.step(action.clone())["next"], env.get_state()))
        torch.testing.assert_close(outs[0][0], outs[1][0], rtol=rtol, atol=atol)
        torch.testing.assert_close(outs[0][1], outs[1][1], rtol=rtol, atol=atol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_restore_replays_the_same_bits(dtype):
    env = TensorHighwayEnv(num_envs=16, seed=3, dtype=dtype, native=True)
    env.reset()
    plays = replayed_twice(env, 40)  # 40 steps: episodes end and rows reset
    torch.testing.assert_close(plays[0], plays[1], rtol=0, atol=0)


def test_threads_split_worlds_without_changing_bits():
    params = tensor_params("highway-fast-v0")
    world = TensorHighwayEnv(num_envs=9, seed=4)._world
    action = torch.arange(9) % 5
    one, out_one = native_step(world, action, params, threads=1)
    three, out_three = native_step(world, action, params, threads=3)
    for a, b in zip(one.vehicles, three.vehicles, strict=True):
        assert torch.equal(a, b)
    assert torch.equal(out_one["observation"], out_three["observation"])


def test_the_input_world_is_left_as_it_was():
    params = tensor_params("highway-fast-v0")
    world = TensorHighwayEnv(num_envs=4, seed=4)._world
    before = [t.clone() for t in world.vehicles]
    native_step(world, torch.full((4,), 3), params)
    assert all(torch.equal(a, b) for a, b in zip(before, world.vehicles, strict=True))


def test_other_scenarios_and_devices_are_refused():
    with pytest.raises(ValueError, match="not 'parking-v0'"):
        native_mode("parking-v0", tensor_params("highway-fast-v0"), torch.device("cpu"))
    with pytest.raises(ValueError, match="on the CPU"):
        native_mode("highway-fast-v0", tensor_params("highway-fast-v0"), torch.device("cuda"))


def test_a_missing_compiler_is_named(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # nothing built there yet
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    native.load_library.cache_clear()
    try:
        with pytest.raises(NativeBuildError, match="no-such-compiler"):
            native.load_library()
    finally:
        native.load_library.cache_clear()


@pytest.mark.parametrize("scenario", ["highway-fast-v0", "highway-v0"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fresh_episodes_hold_the_tensor_paths_bits(scenario, dtype):
    # The reset draws the same streams with the same float64 arithmetic: bit for bit.
    rows = torch.rand(48, generator=torch.Generator().manual_seed(1)) < 0.5
    tensor = TensorHighwayEnv(scenario, num_envs=48, seed=3, dtype=dtype)
    tensor.rollout(3, break_when_any_done=False)  # worlds that moved: resets replace them
    moved = tensor.get_state()
    worlds = []
    for env in (TensorHighwayEnv(scenario, num_envs=48, dtype=dtype, native=True), tensor):
        env.reset(TensorDict(state=moved, batch_size=[48]), set_state=True)
        env.reset(TensorDict(_reset=rows.unsqueeze(-1), batch_size=[48]))
        worlds.append(env.get_state())
    assert (worlds[0] == worlds[1]).all()
    # The control: the reset rows hold new worlds.
    assert not (worlds[0][rows]["vehicles", "x"] == moved[rows]["vehicles", "x"]).all()


def test_config_overrides_agree_with_the_tensor_step():
    # Every key the C++ step reads from the config: lanes, vehicles, frequencies, the
    # ego's initial lane, the target speeds and a different observation table.
    config = {
        "lanes_count": 4,
        "vehicles_count": 12,
        "simulation_frequency": 10,
        "initial_lane_id": 2,
        "vehicles_density": 1.5,
        "action": {"type": "DiscreteMetaAction", "target_speeds": [15, 20, 25, 30, 35]},
        "observation": {
            "type": "Kinematics",
            "vehicles_count": 7,
            "features": ["presence", "x", "y", "vx", "vy", "heading", "cos_h", "sin_h"],
            "absolute": True,
            "see_behind": True,
        },
    }
    envs = [
        TensorHighwayEnv(config=config, num_envs=24, seed=2, dtype=torch.float64, native=flag)
        for flag in (True, False)
    ]
    outs = []
    for env in envs:
        td, steps = env.reset(), []
        for t in range(12):
            td.set("action", (torch.arange(24) + t) % 5)
            out, td = env.step_and_maybe_reset(td)
            steps.append(out["next"])
        outs.append(torch.stack(steps))
    assert outs[0]["observation"].shape[-2:] == (7, 8)
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=1e-9)
