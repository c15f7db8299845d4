"""intersection-v0's traffic in tensors: spawns, exits, packed rows and the narrowed frames."""

from __future__ import annotations

import pytest
import torch

from torchrl_grpo.envs import TensorHighwayEnv, tensor_params
from torchrl_grpo.sim.intersection import INTERSECTION_ACTIONS, intersection_substep, tensor_frames
from torchrl_grpo.sim.intersection_reset import (
    SPAWN_DRAWS,
    check_regulated,
    clear_vehicles,
    empty_intersection,
    spawn_vehicles,
)
from torchrl_grpo.sim.state import world_from_tensordict

SCENARIO = "intersection-v0"


@pytest.fixture(scope="module")
def params():
    return tensor_params(SCENARIO)


def draws(corner: int, goal: int, position: float = 0.0) -> torch.Tensor:
    """One spawn's draws: it is attempted (0.1 < 0.6), exponent 4."""
    return torch.tensor([[0.1, corner, goal, position, 0.0, 4.0]], dtype=torch.float64)


def test_a_spawn_takes_the_first_free_row_with_its_route(params):
    world = empty_intersection(1, params)
    world, stays = spawn_vehicles(world, draws(1, 3), 0.0, 1.0, 1.0, 0.6, params)
    world, again = spawn_vehicles(world, draws(3, 0), 0.0, 1.0, 1.0, 0.6, params)
    assert stays.tolist() == again.tolist() == [True]
    assert world.vehicles.present[0, :4].tolist() == [False, True, True, False]
    # 5 m along corner 1's entry, at 8 m/s, its target speed its speed, its exponent drawn.
    v = world.vehicles
    assert v.lane[0, 1] == params.traffic.entry_lanes[1]
    assert (v.speed[0, 1], v.target_speed[0, 1], v.delta[0, 1]) == (8.0, 8.0, 4.0)
    assert world.route[0, 1, 0] == v.lane[0, 1] and world.route[0, 1, -1] == -1


def test_a_spawn_near_a_vehicle_or_above_the_probability_is_dropped(params):
    world = empty_intersection(1, params)
    world, _ = spawn_vehicles(world, draws(0, 2), 0.0, 1.0, 1.0, 0.6, params)
    # 14 m further along the same entry: within the 15 m clearance.
    near, stays = spawn_vehicles(world, draws(0, 1, 14.0), 0.0, 1.0, 1.0, 0.6, params)
    assert stays.tolist() == [False] and int(near.vehicles.present.sum()) == 1
    far, stays = spawn_vehicles(world, draws(0, 1, 15.5), 0.0, 1.0, 1.0, 0.6, params)
    assert stays.tolist() == [True] and int(far.vehicles.present.sum()) == 2
    unlikely = draws(2, 0)
    unlikely[0, 0] = 0.61  # uniform() above the spawn probability: no attempt
    _, stays = spawn_vehicles(world, unlikely, 0.0, 1.0, 1.0, 0.6, params)
    assert stays.tolist() == [False]


def test_a_full_table_drops_a_spawn_highway_env_would_keep(params):
    # Beyond the duration (the table holds one spawn a step until then): the car is
    # dropped, but the generator advances as highway-env's, which keeps it.
    world = empty_intersection(1, params)
    world = world._replace(vehicles=world.vehicles._replace(present=torch.ones_like(
        world.vehicles.present)))  # fmt: skip
    world.vehicles.x[:] = 500.0  # far from the spawn
    full, stays = spawn_vehicles(world, draws(1, 2), 0.0, 1.0, 1.0, 0.6, params)
    assert stays.tolist() == [True] and torch.equal(full.vehicles.x, world.vehicles.x)


def test_exits_leave_and_the_rows_pack_in_road_order(params):
    world = empty_intersection(1, params)
    for corner in range(4):
        world, _ = spawn_vehicles(
            world, draws(corner, (corner + 1) % 4), 0.0, 1.0, 1.0, 0.6, params
        )
    world = world._replace(ego_rank=torch.tensor([3]))
    world.vehicles.present[0, 0] = True
    exit_lane = params.road.exit.index(True)
    length = params.road.lanes.length[exit_lane]
    s = torch.tensor(length - params.traffic.leave_margin, dtype=torch.float64)
    from torchrl_grpo.sim import lanes as L

    x, y = L.position(s, torch.zeros_like(s), torch.tensor(exit_lane), params.road.lanes)
    world.vehicles.x[0, 2], world.vehicles.y[0, 2], world.vehicles.lane[0, 2] = x, y, exit_lane
    delta = world.vehicles.delta[0, :5].clone()
    cleared = clear_vehicles(world, params)
    assert cleared.vehicles.present[0, :5].tolist() == [True, True, True, True, False]
    assert cleared.vehicles.delta[0, :4].tolist() == [delta[0], delta[1], delta[3], delta[4]]
    assert cleared.ego_rank.tolist() == [2]  # one of the three cars before the ego left
    assert check_regulated(cleared) == []


def test_the_frames_on_the_rows_in_use_are_the_full_tables_bit_for_bit(params):
    env = TensorHighwayEnv(SCENARIO, num_envs=6, seed=2, dtype=torch.float64)
    env.reset()
    world = world_from_tensordict(env.get_state())
    action = torch.tensor(INTERSECTION_ACTIONS, dtype=torch.int64)[torch.tensor([0, 1, 2] * 2)]
    full = world
    for _ in range(15):
        full = intersection_substep(full, action, params)

    narrow = tensor_frames(world, action, 15, params)
    assert 1 + int(world.vehicles.present[:, 1:].sum(1).max()) < params.num_vehicles
    present = full.vehicles.present
    for name in ("x", "y", "heading", "speed", "target_speed", "lane", "crashed"):
        assert torch.equal(
            getattr(full.vehicles, name)[present], getattr(narrow.vehicles, name)[present]
        )
    assert torch.equal(full.yielding, narrow.yielding) and torch.equal(
        full.route_head, narrow.route_head
    )
    assert SPAWN_DRAWS == 6
