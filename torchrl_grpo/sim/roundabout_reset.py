"""Fresh roundabout-v0 worlds from their reset draws: ``RoundaboutEnv._make_vehicles`` in tensors.

highway-env draws a roundabout reset from the env's generator (PCG64) in a fixed
order: for each of the four IDM vehicles, ``normal()`` (its position's offset, times
2 m), ``normal()`` (its speed's, times 2 m/s), ``choice`` of its destination and
``uniform(3.5, 4.5)`` (its IDM exponent). numpy's normals come from its ziggurat, so
the env package replays those 16 draws with numpy on the host
(``torchrl_grpo.envs.highway.roundabout_draws``) and this module builds the worlds from
them: the ego at its spawn with its route to ``nxs``; each IDM vehicle at
``lane.position(s, 0)`` with ``lane.heading_at(s)`` (``make_on_lane``, ``s`` possibly
past the lane's ends), on its closest lane (not always the lane asked for), its route
``[that lane] + shortest path to its destination``, its timer
``(sum(position) * pi) % lane_change_delay``.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("roundabout-v0")
    >>> world = empty_world(1, params.num_vehicles, torch.float64, route_length=params.route_length)
    >>> draws = torch.zeros(1, DRAWS, dtype=torch.float64)
    >>> world = reset_roundabout(world, torch.ones(1, dtype=torch.bool), draws, params)
    >>> world.vehicles.lane[0].tolist()  # the ego, the incoming car, two on the ring, one entering
    [20, 16, 17, 10, 23]
"""

from __future__ import annotations

import functools
import math

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.control import speed_to_index
from torchrl_grpo.sim.fresh_rows import put_rows
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.state import Vehicles, World

__all__ = ["DRAWS", "reset_roundabout", "route_paths"]

#: Reset draws per world: (position normal, speed normal, destination, exponent) per IDM car.
DRAWS = 16


@functools.lru_cache(maxsize=16)
def route_paths(params: RoundaboutParams, device: torch.device) -> torch.Tensor:
    """``[roads, destinations, R - 1]``: each path's legs as codes (a road, no lane), -1 padded.

    A route is ``[its lane] + route_paths(...)[that lane's road, destination]``; a path
    that starts with -1 is empty (that destination cannot be reached from that road, or
    the road ends there).
    """
    road = params.road
    rows = [
        [
            [road.lanes_count + r for r in path] + [-1] * (road.route_length - 1 - len(path))
            for path in per
        ]
        for per in road.paths
    ]
    return torch.tensor(rows, dtype=torch.int64, device=device)


def reset_roundabout(
    world: World, rows: torch.Tensor, draws: torch.Tensor, params: RoundaboutParams
) -> World:
    """``world`` with rows ``rows`` replaced by fresh roundabout worlds built from ``draws``.

    Args:
        world: B worlds with routes (their rows outside ``rows`` are kept).
        rows: ``[B]`` bool, the worlds to reset.
        draws: ``[B, 16]`` float64: per IDM vehicle, ``normal()``, ``normal()``, the
            destination's index among ``traffic.destinations`` (as a float), and
            ``uniform(3.5, 4.5)``.
        params: the constants.

    Returns:
        The worlds, ``time`` and ``steps`` 0 and the ego's speed index set on ``rows``.

    Example:
        >>> # see the module's example
    """
    v, t = world.vehicles, params.traffic
    device = v.x.device
    n = v.x.shape[1]
    if draws.dtype != torch.float64:
        raise ValueError(f"roundabout reset draws must be float64, got {draws.dtype}")
    # Only the reset rows are built (a few of a batch each step), then put in place.
    reset = rows.to(device).nonzero().squeeze(-1)
    if reset.numel() == 0:
        return world
    draws = draws.to(device)[reset]
    batch = reset.numel()
    geo = params.road.lanes
    f64 = dict(dtype=torch.float64, device=device)
    full = functools.partial(torch.full, (batch,), **f64)
    spawn = [torch.full((batch,), t.ego_lane, device=device)]
    s_col, speed_col = [full(t.ego_s)], [full(t.ego_speed)]
    for k, (lane, s0) in enumerate(zip(t.spawn_lanes, t.spawn_s, strict=True)):
        spawn.append(torch.full((batch,), lane, device=device))
        s_col.append(s0 + draws[:, 4 * k] * t.position_scale)
        speed_col.append(t.spawn_speed + draws[:, 4 * k + 1] * t.speed_scale)
    spawn_lane, s = torch.stack(spawn, 1), torch.stack(s_col, 1)
    x, y = L.position(s, torch.zeros_like(s), spawn_lane, geo)
    heading = L.heading_at(s, spawn_lane, geo)
    heading[:, 0] = t.ego_heading
    speed = torch.stack(speed_col, 1)
    lane = L.closest_lane(x, y, heading, geo)
    index = speed_to_index(speed[:, 0], params.control.target_speeds)
    target_speed = speed.clone()
    target_speed[:, 0] = torch.tensor(params.control.target_speeds, **f64)[index]
    timer = torch.remainder((x + y) * math.pi, params.idm.lane_change_delay)
    timer[:, 0] = 0.0
    delta = torch.cat([torch.zeros(batch, 1, **f64), draws[:, 3::4]], 1)
    choice = torch.tensor(t.destinations, device=device)[draws[:, 2::4].to(torch.int64)]
    goal = torch.cat([torch.full((batch, 1), t.ego_destination, device=device), choice], 1)
    road_of = torch.tensor(params.road.road, device=device)
    route = torch.cat([lane.unsqueeze(-1), route_paths(params, device)[road_of[lane], goal]], -1)
    zeros = torch.zeros(batch, n, **f64)
    flags = torch.zeros(batch, n, dtype=torch.bool, device=device)
    fresh = Vehicles(
        x=x, y=y, heading=heading, speed=speed, target_speed=target_speed, steering=zeros,
        acceleration=zeros, timer=timer, delta=delta, impact_x=zeros, impact_y=zeros,
        lane=lane, target_lane=lane.clone(), crashed=flags, impact=flags,
        check_collisions=torch.full_like(flags, t.others_check_collisions) | (
            torch.arange(n, device=device) == 0),
        present=torch.ones_like(flags),
    )  # fmt: skip
    return put_rows(world, reset, fresh, index, route=route, route_head=torch.zeros_like(lane))
