"""The lane geometry against highway-env's own lane objects, on many random points.

Straight lanes (the merge road's, axis-aligned) must match bit for bit; sine and
circular lanes go through sin, cos, atan2 and arctan, where torch's CPU kernels and
numpy's differ by an ulp on a few inputs (docs/sim.md): 1e-12 there.
"""

from __future__ import annotations

import gymnasium as gym
import highway_env  # noqa: F401
import numpy as np
import pytest
import torch

from torchrl_grpo.envs.highway.lane_constants import road_graph
from torchrl_grpo.sim import lanes as L


def _network(scenario: str):
    env = gym.make(scenario)
    env.reset(seed=0)
    return env.unwrapped.road.network


@pytest.fixture(scope="module", params=["merge-v0", "roundabout-v0"])
def road(request):
    network = _network(request.param)
    return network, road_graph(network)


def _points(n: int, seed: int = 0):
    g = np.random.default_rng(seed)
    # Around every lane of both roads: x in [-60, 480], y in [-60, 200].
    x = g.uniform(-60, 480, n)
    y = g.uniform(-60, 200, n)
    h = g.uniform(-7, 7, n)
    return x, y, h


def _tol(lane) -> float:
    return 0.0 if type(lane).__name__ == "StraightLane" else 1e-12


def test_lane_functions_match_highway_env(road):
    network, graph = road
    x, y, h = _points(400)
    tx, ty = torch.from_numpy(x), torch.from_numpy(y)
    for k, key in enumerate(graph.keys):
        lane = network.get_lane(key)
        idx = torch.full((len(x),), k)
        s, r = L.local_coordinates(tx, ty, idx, graph.geometry)
        ref = np.array(
            [lane.local_coordinates(np.array([a, b])) for a, b in zip(x, y, strict=True)]
        )
        tol = _tol(lane)
        np.testing.assert_allclose(s.numpy(), ref[:, 0], rtol=0, atol=tol * 500)
        np.testing.assert_allclose(r.numpy(), ref[:, 1], rtol=0, atol=tol * 500)
        # Thresholds from highway-env's own (s, r), so a 1e-12 drift cannot flip a test.
        rs, rr = torch.from_numpy(ref[:, 0]), torch.from_numpy(ref[:, 1])
        on = [lane.on_lane(np.array([a, b]), margin=1) for a, b in zip(x, y, strict=True)]
        assert L.on_lane(rs, rr, idx, graph.geometry, margin=1).tolist() == on
        reach = [lane.is_reachable_from(np.array([a, b])) for a, b in zip(x, y, strict=True)]
        assert L.is_reachable(rs, rr, idx, graph.geometry).tolist() == reach
        end = [lane.after_end(np.array([a, b])) for a, b in zip(x, y, strict=True)]
        assert L.after_end(rs, idx, graph.geometry).tolist() == end
        heading = L.heading_at(rs, idx, graph.geometry).numpy()
        np.testing.assert_allclose(heading, [lane.heading_at(v) for v in ref[:, 0]], atol=tol)
        px, py = L.position(rs, rr, idx, graph.geometry)
        back = np.array([lane.position(a, b) for a, b in ref])
        np.testing.assert_allclose(px.numpy(), back[:, 0], rtol=0, atol=tol * 500)
        np.testing.assert_allclose(py.numpy(), back[:, 1], rtol=0, atol=tol * 500)


def test_distance_and_closest_lane_match_highway_env(road):
    network, graph = road
    x, y, h = _points(600, seed=1)
    d = L.distance_with_heading(
        torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(h), graph.geometry
    ).numpy()
    lanes = [network.get_lane(key) for key in graph.keys]
    ref = np.array(
        [
            [ln.distance_with_heading(np.array([a, b]), c) for ln in lanes]
            for a, b, c in zip(x, y, h, strict=True)
        ]
    )
    np.testing.assert_allclose(d, ref, rtol=0, atol=1e-9)
    closest = L.closest_lane(
        torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(h), graph.geometry
    ).tolist()
    expected = [
        graph.keys.index(network.get_closest_lane_index(np.array([a, b]), c))
        for a, b, c in zip(x, y, h, strict=True)
    ]
    agree = np.mean(np.array(closest) == np.array(expected))
    assert agree == 1.0


def test_merge_straight_lanes_are_bitwise():
    network = _network("merge-v0")
    graph = road_graph(network)
    x, y, _ = _points(300, seed=2)
    for k, key in enumerate(graph.keys[:8]):  # the sine lane (k, b, 0) is last
        lane = network.get_lane(key)
        s, r = L.local_coordinates(
            torch.from_numpy(x), torch.from_numpy(y), torch.full((300,), k), graph.geometry
        )
        ref = np.array(
            [lane.local_coordinates(np.array([a, b])) for a, b in zip(x, y, strict=True)]
        )
        assert np.array_equal(s.numpy(), ref[:, 0]) and np.array_equal(r.numpy(), ref[:, 1])


def test_next_lane_table_matches_network():
    network = _network("merge-v0")
    graph = road_graph(network)
    for k, key in enumerate(graph.keys):
        lane = network.get_lane(key)
        for s in np.linspace(lane.length - 2.4, lane.length + 4, 7):
            for r in (-1.5, 0.0, 1.5):
                nxt = network.next_lane(key, route=None, position=lane.position(s, r))
                assert graph.keys[graph.next_lane[k]] == nxt, (key, s, r)
