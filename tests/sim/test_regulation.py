"""The right-of-way pass against highway-env's own RegulatedRoad, pair by pair.

Worlds recorded from highway-env's intersection-v0, and the same worlds with every
speed scaled (more predicted trajectories meet), are read into tensors; every pair of
vehicles in road order gets ``is_conflict_possible`` and ``respect_priorities`` from
highway-env and from :mod:`torchrl_grpo.sim.regulation`.
"""

from __future__ import annotations

import itertools

import pytest
import torch
from highway_env.road.regulation import RegulatedRoad

from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv
from torchrl_grpo.envs.highway.parity import record_worlds
from torchrl_grpo.envs.highway.parity_policies import recording_policies
from torchrl_grpo.sim.regulation import (
    NEVER,
    YIELDED,
    YIELDING,
    conflicts,
    enforce_road_rules,
    predict_along_route,
)
from torchrl_grpo.sim.state import map_world

SCENARIO = "intersection-v0"


@pytest.fixture(scope="module")
def worlds():
    env = TensorHighwayEnv(SCENARIO, num_envs=1, dtype=torch.float64)
    states, _ = record_worlds(SCENARIO, recording_policies(SCENARIO, env.config), 30, seed=3)
    return env, states


def road_ordered(env, state, scale):
    """The world of ``state`` (speeds times ``scale``) with rows in road order, and hw's."""
    hw = HighwayEnv(SCENARIO)
    hw.set_state(state)
    road = hw.gym_env.unwrapped.road
    for v in road.vehicles:
        v.speed *= scale
    world, _, _ = env.bridge.read(hw.get_state())
    n, rank = int(world.vehicles.present.sum()), int(world.ego_rank)
    order = torch.tensor([*range(1, rank + 1), 0, *range(rank + 1, n)])
    world = map_world(lambda t: t[:, order] if t.ndim > 1 else t, world)
    return world, road


@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_conflicts_and_yields_are_highway_envs(worlds, scale):
    env, states = worlds
    params = env.params
    pairs = met = 0
    for state in states:
        world, road = road_ordered(env, state, scale)
        mine = conflicts(world.vehicles, world.route, world.route_head, params)[0]
        _, flags = enforce_road_rules(
            world.vehicles, world.route, world.route_head, world.yielding, params,
            ego_row=world.ego_rank,
        )  # fmt: skip
        vehicles = road.vehicles
        yielders = set()
        for i, j in itertools.combinations(range(len(vehicles)), 2):
            theirs = RegulatedRoad.is_conflict_possible(vehicles[i], vehicles[j])
            assert bool(mine[i, j]) == bool(theirs), (i, j)
            pairs += 1
            if theirs:
                met += 1
                yielder = RegulatedRoad.respect_priorities(vehicles[i], vehicles[j])
                if yielder is not hw_ego(road):
                    yielders.add(vehicles.index(yielder))
        assert {int(k) for k in (flags[0] == YIELDING).nonzero().flatten()} == yielders
    assert pairs > 1000 and met > 0


def hw_ego(road):
    return next(v for v in road.vehicles if type(v).__name__ == "MDPVehicle")


def test_predictions_follow_the_route_as_highway_env_does(worlds):
    env, states = worlds
    times = torch.tensor(env.params.regulation.times, dtype=torch.float64).numpy()
    for state in states[::3]:
        world, road = road_ordered(env, state, 1.0)
        x, y, h = predict_along_route(world.vehicles, world.route, world.route_head, env.params)
        for k, v in enumerate(road.vehicles):
            positions, headings = v.predict_trajectory_constant_speed(times)
            got = torch.stack([x[0, k], y[0, k]], -1)
            assert torch.allclose(got, torch.tensor(positions), atol=1e-9), k
            assert torch.allclose(h[0, k], torch.tensor(headings, dtype=torch.float64), atol=1e-9)


def test_a_yield_lasts_until_the_next_pass(worlds):
    # YIELD_DURATION is 0: at the next pass every yielding car gets the speed limit back.
    env, states = worlds
    world, _ = road_ordered(env, states[0], 1.0)
    was = torch.full_like(world.yielding, YIELDING)
    was[0, 0] = NEVER
    alone = world.vehicles._replace(present=torch.zeros_like(world.vehicles.present))
    speed, flags = enforce_road_rules(
        alone, world.route, world.route_head, was, env.params, ego_row=world.ego_rank
    )
    assert flags[0, 0] == NEVER and bool((flags[0, 1:] == YIELDED).all())
    assert bool((speed[0, 1:] == env.params.road.speed_limit).all())
