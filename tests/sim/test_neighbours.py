"""The sorted neighbour search against a plain restatement of highway-env's scan."""

import torch

from torchrl_grpo.sim.neighbours import lane_index, neighbours
from torchrl_grpo.sim.params import RoadParams

ROAD = RoadParams(
    lanes_count=4, lane_width=4.0, lane_length=10000.0, speed_limit=30.0, margin_length=5.0
)


def scan(x, y, present, i, lane):
    """``Road.neighbour_vehicles(vehicles[i], lane)`` on one world, as highway-env loops."""
    s = float(x[i])
    s_front = s_rear = None
    front = rear = -1
    for j in range(len(x)):
        if j == i or not present[j]:
            continue
        lat = float(y[j]) - lane * ROAD.lane_width
        s_v = float(x[j])
        if not (abs(lat) <= ROAD.lane_width / 2 + 1 and -5 <= s_v < 10005):
            continue
        if s <= s_v and (s_front is None or s_v <= s_front):
            s_front, front = s_v, j
        if s_v < s and (s_rear is None or s_v > s_rear):
            s_rear, rear = s_v, j
    return front, rear


def test_matches_highway_env_scan_with_ties_absent_rows_and_the_road_ends():
    g = torch.Generator().manual_seed(0)
    batch, n = 60, 10
    # Positions on a 5 m grid: many exact ties; some before the road's start.
    x = torch.randint(0, 6, (batch, n), generator=g).double() * 5.0 - 6.0
    y = torch.rand(batch, n, generator=g, dtype=torch.float64) * 16 - 2  # between lanes too
    present = torch.rand(batch, n, generator=g) > 0.1
    index = lane_index(x, y, present, ROAD)
    rows = torch.arange(batch).repeat_interleave(4 * n)
    vehicle = torch.arange(n).repeat(4).repeat(batch)
    lane = torch.arange(4).repeat_interleave(n).repeat(batch)
    front, rear = neighbours(index, rows, vehicle, lane)
    for q in range(len(rows)):
        b, i, lane_id = int(rows[q]), int(vehicle[q]), int(lane[q])
        if present[b, i]:
            assert (int(front[q]), int(rear[q])) == scan(x[b], y[b], present[b], i, lane_id), q


def test_a_vehicle_between_two_lanes_is_in_both():
    x = torch.tensor([[0.0, 20.0]])
    y = torch.tensor([[2.0, 6.0]])  # vehicle 1 at 6 m: 2 m from lane 1, 2 m from lane 2
    index = lane_index(x, y, torch.ones(1, 2, dtype=torch.bool), ROAD)
    zero = torch.zeros(2, dtype=torch.int64)
    front, _ = neighbours(index, zero, zero, torch.tensor([1, 2]))
    assert front.tolist() == [1, 1]
