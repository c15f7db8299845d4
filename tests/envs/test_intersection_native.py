"""intersection-v0's C++ frames (``TensorHighwayEnv("intersection-v0", native=True)``).

Two references: highway-env itself, through the parity ladder's rungs a to c on worlds
recorded from highway-env runs (turns, yields, arrivals, exits and spawns; in
test_routed_native.py, with merge-v0's and roundabout-v0's), and the tensor frames,
which the C++ frames follow expression by expression. Free rows of the
table are left as they were by the C++ frames (a spawn writes all of a row), so the
comparisons with the tensor path read the present vehicles.
"""

from __future__ import annotations

import pytest
import torch
from env_helpers import stepped_states
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import TensorHighwayEnv, tensor_params
from torchrl_grpo.sim.intersection import tensor_frames
from torchrl_grpo.sim.intersection_native import native_frames
from torchrl_grpo.sim.regulation import YIELDING
from torchrl_grpo.sim.routed_native import routed_step
from torchrl_grpo.sim.state import world_from_tensordict
from torchrl_grpo.training.env_builder import steps_natively

SCENARIO = "intersection-v0"
SLOWER, IDLE, FASTER = 4, 1, 3  # the meta-actions the frames take


def _worlds(batch: int, steps: int, dtype=torch.float64) -> list:
    """The tensor env's worlds after each of ``steps`` random steps (finished rows reset)."""
    return [world_from_tensordict(s) for s in stepped_states(SCENARIO, dtype, steps, batch)]


def _present_gap(one, two) -> tuple[float, int]:
    """(largest float difference, count of discrete differences) over present vehicles."""
    present = one.vehicles.present
    assert torch.equal(present, two.vehicles.present)
    worst, differ = 0.0, 0
    for a, b in zip(one.vehicles, two.vehicles, strict=True):
        if a.dtype.is_floating_point:
            worst = max(worst, float(((a - b).abs() * present).max()))
        else:
            differ += int(((a != b) & present).sum())
    for a, b in ((one.route_head, two.route_head), (one.yielding, two.yielding)):
        differ += int(((a != b) & present).sum())
    differ += int((one.road_steps != two.road_steps).sum() + (one.steps != two.steps).sum())
    return worst, differ


def test_specs_and_rollout():
    env = TensorHighwayEnv(SCENARIO, num_envs=6, seed=1, native=True)
    assert env.step_mode == "native"
    check_env_specs(env)
    assert env.rollout(4, break_when_any_done=False)["next", "reward"].shape == (6, 4, 1)


def test_a_step_of_frames_agrees_with_the_tensor_frames_in_float64():
    # An ulp of a sine or an arcsine (libm's against torch's) grows through 15 frames
    # (the largest gap seen, 1.5e-6, on a steering angle); every discrete field agrees.
    yields = crashes = 0
    for k, world in enumerate(_worlds(32, 9)[2::3]):
        action = torch.tensor([SLOWER, IDLE, FASTER])[torch.arange(32) % 3]
        native = native_frames(world, action, 15, tensor_params(SCENARIO))
        tensor = tensor_frames(world, action, 15, tensor_params(SCENARIO))
        worst, differ = _present_gap(native, tensor)
        assert worst <= 1e-5 and differ == 0, (k, worst, differ)
        yields += int((tensor.yielding == YIELDING).sum())
        crashes += int(tensor.vehicles.crashed.sum())
    assert yields > 0 and crashes > 0  # the comparison covered right of way and crashes


def test_fresh_worlds_warm_up_in_cpp_as_with_tensors():
    tensor = TensorHighwayEnv(SCENARIO, num_envs=16, seed=9, dtype=torch.float64)
    native = TensorHighwayEnv(SCENARIO, num_envs=16, seed=9, dtype=torch.float64, native=True)
    tensor.reset()
    native.reset()
    worst, differ = _present_gap(native._world, tensor._world)
    assert worst <= 1e-9 and differ == 0
    assert torch.equal(native._world.ego_rank, tensor._world.ego_rank)


def test_a_restore_replays_the_same_bits():
    env = TensorHighwayEnv(SCENARIO, num_envs=12, seed=3, dtype=torch.float32, native=True)
    td = env.reset()
    root = env.get_state()
    g = torch.Generator().manual_seed(0)
    actions = [torch.randint(0, 3, (12,), generator=g) for _ in range(14)]  # rows end, reset
    plays = []
    for _ in range(2):
        td = env.reset(TensorDict(state=root, batch_size=[12]), set_state=True)
        rewards = []
        for action in actions:
            out, td = env.step_and_maybe_reset(td.set("action", action))
            rewards.append(out["next", "reward"])
        plays.append((torch.stack(rewards), env.get_state()))
    torch.testing.assert_close(plays[0], plays[1], rtol=0, atol=0)


def test_threads_split_worlds_without_changing_bits():
    world = _worlds(70, 3, torch.float32)[-1]
    action = torch.full((70,), FASTER)
    one = native_frames(world, action, 15, tensor_params(SCENARIO), threads=1)
    three = native_frames(world, action, 15, tensor_params(SCENARIO), threads=3)
    for a, b in zip((*one.vehicles, one.yielding), (*three.vehicles, three.yielding), strict=True):
        assert torch.equal(a, b)


def test_the_input_world_is_left_as_it_was():
    world = _worlds(4, 2)[-1]
    tables = (*world.vehicles, world.route_head, world.yielding, world.road_steps)
    before = [t.clone() for t in tables]
    native_frames(world, torch.full((4,), FASTER), 15, tensor_params(SCENARIO))
    assert all(torch.equal(a, b) for a, b in zip(before, tables, strict=True))


def test_errors_name_the_problem_and_the_env_steps_on():
    params = tensor_params(SCENARIO)
    env = TensorHighwayEnv(SCENARIO, num_envs=2, seed=0, native=True)
    world = env._world
    with pytest.raises(ValueError, match="intersection-v0's frames"):
        routed_step(world, torch.zeros(2, dtype=torch.int64), params)
    no_rules = TensorHighwayEnv("roundabout-v0", num_envs=2, seed=0)._world
    with pytest.raises(ValueError, match="with routes and yield states"):
        native_frames(no_rules, torch.ones(2, dtype=torch.int64), 15, params)
    with pytest.raises(ValueError, match="frames must be >= 0, got -1"):
        native_frames(world, torch.ones(2, dtype=torch.int64), -1, params)
    with pytest.raises(ValueError, match="ego rank outside the table's 24 rows"):
        native_frames(world._replace(ego_rank=torch.tensor([0, 24])), torch.ones(2), 15, params)
    assert env.rollout(2)["next", "reward"].shape == (2, 2, 1)


def test_training_steps_the_intersection_in_cpp_by_default():
    cfg = OmegaConf.create({"backend": "auto", "scenario": SCENARIO, "config": {}})
    assert steps_natively(cfg)
    assert not steps_natively(OmegaConf.merge(cfg, {"backend": "tensor"}))
