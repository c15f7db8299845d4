"""check_world names every entry that does not fit, and admits what highway-env reaches."""

import torch
from sim_helpers import fresh_world

from torchrl_grpo.sim import check_world, empty_world, world_from_tensordict, world_to_tensordict


def test_a_fresh_world_fits(fast_params):
    assert check_world(fresh_world(fast_params, 3), fast_params) == []


def test_reachable_extremes_are_admitted(fast_params):
    world = fresh_world(fast_params, 2)
    v = world.vehicles
    v.speed[0, 1] = -3.0  # speeds below 0 happen (a crashed vehicle overshoots)
    v.speed[0, 2] = 45.0  # speed itself is never clipped
    v.heading[1, 0] = 7.5  # headings are not wrapped
    assert check_world(world, fast_params) == []


def test_each_corruption_is_named(fast_params):
    cases = {
        ("speed", float("nan")): "vehicles.speed",
        ("x", float("inf")): "vehicles.x",
        ("timer", float("-inf")): "vehicles.timer",
        ("lane", 3): "vehicles.lane",
        ("target_lane", -1): "vehicles.target_lane",
    }
    for (name, value), entry in cases.items():
        world = fresh_world(fast_params, 2)
        getattr(world.vehicles, name)[1, 2] = value
        problems = check_world(world, fast_params)
        assert len(problems) == 1 and problems[0].startswith(entry) and "[1]" in problems[0]
    world = fresh_world(fast_params, 2)
    world.vehicles.check_collisions[0, 3] = True  # highway-fast-v0's others never check
    world.speed_index[1] = 7
    world.vehicles.present[0, 0] = False
    names = sorted(p.split(":")[0] for p in check_world(world, fast_params))
    assert names == ["speed_index", "vehicles.check_collisions", "vehicles.present"]


def test_a_world_of_another_size_is_refused(fast_params, v0_params):
    problems = check_world(fresh_world(v0_params, 1), fast_params)
    assert problems and "[B, 21]" in problems[0]


def test_tensordict_round_trip_is_exact(fast_params):
    world = fresh_world(fast_params, 4)
    back = world_from_tensordict(world_to_tensordict(world).clone())
    assert all(torch.equal(a, b) for a, b in zip(world.vehicles, back.vehicles, strict=True))
    assert all(torch.equal(a, b) for a, b in zip(world[1:6], back[1:6], strict=True))
    assert back.route is None and back.route_head is None  # the highway has no routes


def test_routes_round_trip_through_the_tensordict():
    world = empty_world(2, 3, route_length=4)
    world.route[1, 2] = torch.tensor([5, 40, -1, -1])
    world.route_head[1, 2] = 1
    td = world_to_tensordict(world)
    assert td["route"].batch_size == torch.Size([2, 3])
    back = world_from_tensordict(td.clone())
    assert torch.equal(back.route, world.route) and torch.equal(back.route_head, world.route_head)
