"""routes.next_lane against highway-env's own RoadNetwork.next_lane on the roundabout."""

from __future__ import annotations

import copy

import gymnasium as gym
import highway_env  # noqa: F401 - registers the scenarios
import numpy as np
import pytest
import torch

from torchrl_grpo.envs import tensor_params
from torchrl_grpo.envs.highway.lane_constants import lane_keys
from torchrl_grpo.sim.routes import next_lane


@pytest.fixture(scope="module")
def roundabout():
    env = gym.make("roundabout-v0")
    env.reset(seed=0)
    network = env.unwrapped.road.network
    params = tensor_params("roundabout-v0")
    keys = lane_keys(network)
    roads = list(dict.fromkeys(k[:2] for k in keys))
    return network, params.road, keys, roads


def encode(route, keys, roads, road) -> list[int]:
    codes = [
        keys.index(leg) if leg[2] is not None else road.lanes_count + roads.index(leg[:2])
        for leg in route
    ]
    return codes + [-1] * (road.route_length - len(codes))


def test_without_routes_every_lane_end_hands_over_as_highway_env(roundabout):
    network, road, keys, roads = roundabout
    cases = []
    for key in keys:
        lane = network.get_lane(key)
        for lateral in (-1.5, 0.0, 0.7):
            cases.append((key, lane.position(lane.length - 1.0, lateral)))
    x = torch.tensor([[float(p[0]) for _, p in cases]], dtype=torch.float64)
    y = torch.tensor([[float(p[1]) for _, p in cases]], dtype=torch.float64)
    target = torch.tensor([[keys.index(k) for k, _ in cases]])
    route = torch.full((1, len(cases), road.route_length), -1)
    head = torch.zeros(1, len(cases), dtype=torch.int64)
    mine, heads = next_lane(x, y, target, route, head, road)
    theirs = [keys.index(network.next_lane(k, route=None, position=p)) for k, p in cases]
    assert mine[0].tolist() == theirs
    assert heads.eq(0).all()


def test_planned_routes_drop_their_legs_and_pick_lanes_as_highway_env(roundabout):
    network, road, keys, roads = roundabout
    rng = np.random.default_rng(0)
    cases = []
    for key in keys:
        if key[1] not in network.graph:
            continue  # no road leaves the lane's end
        lane = network.get_lane(key)
        for destination in ("exr", "sxr", "nxr", "wxr", "nxs"):
            path = network.shortest_path(key[1], destination)
            route = [key] + [(a, b, None) for a, b in zip(path, path[1:], strict=False)]
            position = lane.position(lane.length - 1.0, float(rng.uniform(-2, 2)))
            cases.append((key, route, position))
            # A route whose head is not the lane's road (a mismatch: the closest road wins).
            cases.append((key, route[1:], position))
    x = torch.tensor([[float(p[0]) for *_, p in cases]], dtype=torch.float64)
    y = torch.tensor([[float(p[1]) for *_, p in cases]], dtype=torch.float64)
    target = torch.tensor([[keys.index(k) for k, *_ in cases]])
    legs = torch.tensor([[encode(r, keys, roads, road) for _, r, _ in cases]])
    head = torch.zeros(1, len(cases), dtype=torch.int64)
    mine, heads = next_lane(x, y, target, legs, head, road)
    theirs, dropped = [], []
    for key, route, position in cases:
        left = copy.copy(route)
        theirs.append(keys.index(network.next_lane(key, route=left, position=position)))
        dropped.append(len(route) - len(left))
    assert mine[0].tolist() == theirs
    assert heads[0].tolist() == dropped
