"""Right of way at an intersection: ``RegulatedRoad.enforce_road_rules`` in tensors.

Every ``regulation.every`` road frames, before the vehicles move:

1. every vehicle that was yielding gets its lane's speed limit back as target speed
   (``YIELD_DURATION`` is 0, so a yield lasts until the next pass);

A vehicle's yield state is an int8: :data:`NEVER` (highway-env's vehicle has no
``is_yielding``), :data:`YIELDED` (``is_yielding`` False) or :data:`YIELDING`.

2. every pair of present vehicles whose predicted trajectories meet
   (``is_conflict_possible``) names a yielding vehicle (``respect_priorities``): the one
   on the lane of lower priority, or at equal priority the one behind. If it is an IDM
   vehicle (not the ego), its target speed becomes 0 and it is yielding.

A prediction (``predict_trajectory_constant_speed``) places the vehicle at
``s + speed * t`` along its remaining route, ``s`` read on its CURRENT lane, for
``t`` in ``regulation.times``; two predictions meet at a time where their centres are
at most one length apart and one's 9 points (corners, centre, edge midpoints) lie in
the other's rectangle (``rotated_rectangles_intersect``, rectangles of 1.5 lengths by
0.9 widths). highway-env's ``point_in_rotated_rectangle`` turns the point by ``+angle``
(not ``-angle``), and so does this module.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("intersection-v0")
    >>> w = empty_world(1, 3, torch.float64, route_length=params.route_length, regulated=True)
    >>> v = w.vehicles._replace(  # the ego and a car 4 m behind it on an entry, 8 m/s
    ...     x=torch.tensor([[2.0, 2.0, 50.0]], dtype=torch.float64),
    ...     y=torch.tensor([[60.0, 64.0, 50.0]], dtype=torch.float64),
    ...     heading=torch.full((1, 3), -1.5707963267948966, dtype=torch.float64),
    ...     speed=torch.full((1, 3), 8.0, dtype=torch.float64),
    ...     present=torch.tensor([[True, True, False]]))
    >>> route = torch.full_like(w.route, -1)
    >>> speed, flags = enforce_road_rules(v, route, w.route_head, w.yielding, params)
    >>> flags.tolist(), speed[0, 1].item()  # the car behind (row 1, at y = 64) yields
    ([[0, 2, 0]], 0.0)
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.routes import road_tables
from torchrl_grpo.sim.state import Vehicles

__all__ = ["NEVER", "YIELDED", "YIELDING", "conflicts", "enforce_road_rules", "predict_along_route"]

#: Yield states: never yielded, yielded and released, yielding now.
NEVER, YIELDED, YIELDING = 0, 1, 2


def predict_along_route(
    v: Vehicles, route: torch.Tensor, head: torch.Tensor, params
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``position_heading_along_route`` at ``regulation.times``: ``[B, N, T]`` x, y, heading.

    The route is the legs from the head on (the current lane if none is left); a leg
    without a lane takes the current lane's id (every intersection road has one lane).

    Example:
        >>> # see the module's example
    """
    road, geo = params.road, params.road.lanes
    times = torch.tensor(params.regulation.times, dtype=v.x.dtype, device=v.x.device)
    s0, _ = L.local_coordinates(v.x, v.y, v.lane, geo)
    s = s0.unsqueeze(-1) + v.speed.unsqueeze(-1) * times  # [B, N, T]
    tab = road_tables(road, v.x.device)
    length = route.shape[-1]
    steps = torch.arange(length, device=v.x.device)
    at = head.unsqueeze(-1) + steps  # [B, N, R]: the remaining legs
    legs = route.gather(-1, at.clamp(max=length - 1))
    legs = torch.where(at < length, legs, -1)
    own_id = tab["lane_id"][v.lane].unsqueeze(-1)
    lanes_of_road = tab["lanes"][tab["road"][legs.clamp(min=0)]]  # [B, N, R, W]
    by_road = lanes_of_road.gather(-1, own_id.unsqueeze(-1).expand(*legs.shape, 1)).squeeze(-1)
    leg_lane = torch.where(legs < road.lanes_count, legs, by_road)
    count = (legs >= 0).sum(-1)  # legs are -1 padded at the end
    leg_lane = torch.where(count.unsqueeze(-1) > 0, leg_lane, v.lane.unsqueeze(-1))
    count = count.clamp(min=1)
    lengths = torch.tensor(geo.length, dtype=v.x.dtype, device=v.x.device)
    index = torch.zeros_like(s, dtype=torch.int64)
    for k in range(length - 1):
        lane_k = leg_lane[..., k : k + 1].clamp(min=0)
        here = lengths[lane_k]
        moves = (index == k) & (count.unsqueeze(-1) > k + 1) & (s > here)
        s = torch.where(moves, s - here, s)
        index = index + moves.to(torch.int64)
    lane = leg_lane.clamp(min=0).gather(-1, index)
    x, y = L.position(s, torch.zeros_like(s), lane, geo)
    return x, y, L.heading_at(s, lane, geo)


def _corners(x, y, heading, length: float, width: float):
    """``rect_corners(include_midpoints=True, include_center=True)``: ``[..., 9]`` x and y."""
    hl, hw = length / 2, width / 2
    px = torch.tensor([-hl, -hl, hl, hl, 0.0, -hl, hl, 0.0, 0.0], dtype=x.dtype, device=x.device)
    py = torch.tensor([-hw, hw, hw, -hw, 0.0, 0.0, 0.0, -hw, hw], dtype=x.dtype, device=x.device)
    c, s = torch.cos(heading).unsqueeze(-1), torch.sin(heading).unsqueeze(-1)
    return c * px + -s * py + x.unsqueeze(-1), s * px + c * py + y.unsqueeze(-1)


def _inside(px, py, x, y, heading, length: float, width: float) -> torch.Tensor:
    """Any of the points ``[..., 9]`` in the rectangle (``point_in_rotated_rectangle``)."""
    c, s = torch.cos(heading).unsqueeze(-1), torch.sin(heading).unsqueeze(-1)
    dx, dy = px - x.unsqueeze(-1), py - y.unsqueeze(-1)
    ux, uy = c * dx + -s * dy, s * dx + c * dy
    return ((-length / 2 <= ux) & (ux <= length / 2) & (-width / 2 <= uy) & (uy <= width / 2)).any(
        -1
    )


def conflicts(v: Vehicles, route: torch.Tensor, head: torch.Tensor, params) -> torch.Tensor:
    """``[B, N, N]``: ``is_conflict_possible`` of each pair ``i < j`` of present vehicles.

    Example:
        >>> # see the module's example
    """
    x, y, h = predict_along_route(v, route, head, params)
    n = v.x.shape[1]
    dx = x.unsqueeze(1) - x.unsqueeze(2)  # [B, i, j, T] = x_j - x_i
    dy = y.unsqueeze(1) - y.unsqueeze(2)
    near = ~(torch.sqrt(dx * dx + dy * dy) > params.vehicle.length)
    pair = v.present.unsqueeze(2) & v.present.unsqueeze(1)
    upper = torch.ones(n, n, dtype=torch.bool, device=v.x.device).triu(1)
    near = near & (pair & upper).unsqueeze(-1)
    b, i, j, t = near.nonzero(as_tuple=True)
    out = torch.zeros_like(pair)
    if b.numel() == 0:
        return out
    reg = params.regulation
    size = (reg.length_scale * params.vehicle.length, reg.width_scale * params.vehicle.width)
    one = (x[b, i, t], y[b, i, t], h[b, i, t])
    two = (x[b, j, t], y[b, j, t], h[b, j, t])
    meet = _inside(*_corners(*one, *size), *two, *size) | _inside(
        *_corners(*two, *size), *one, *size
    )
    return out.index_put_((b[meet], i[meet], j[meet]), torch.ones_like(b[meet], dtype=torch.bool))


def enforce_road_rules(
    v: Vehicles,
    route: torch.Tensor,
    head: torch.Tensor,
    yielding: torch.Tensor,
    params,
    ego_row: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One rule pass: ``(target speeds, yield states)``, both ``[B, N]``.

    Args:
        v: the vehicle table, rows in ``road.vehicles`` order (pairs ``i < j`` are
            ``respect_priorities(v_i, v_j)``: at equal priority and distance, j yields).
        route: ``[B, N, R]`` route legs.
        head: ``[B, N]`` route heads.
        yielding: ``[B, N]`` int8 yield states.
        params: the intersection's constants.
        ego_row: ``[B]`` the ego's row, which never yields (default: row 0).

    Example:
        >>> # see the module's example
    """
    now = yielding == YIELDING
    target = torch.where(now, torch.full_like(v.x, params.road.speed_limit), v.target_speed)
    state = torch.where(now, torch.full_like(yielding, YIELDED), yielding)
    meet = conflicts(v, route, head, params)
    priority = torch.tensor(params.road.priority, device=v.x.device)[v.lane]
    p_i, p_j = priority.unsqueeze(2), priority.unsqueeze(1)
    dx = v.x.unsqueeze(1) - v.x.unsqueeze(2)  # [b, i, j] = x_j - x_i
    dy = v.y.unsqueeze(1) - v.y.unsqueeze(2)
    c, s = torch.cos(v.heading), torch.sin(v.heading)
    # front_distance_to: np.dot of 2-vectors, fma(s, dy, c * dx) as in lanes.local_coordinates.
    ahead_of_i = torch.addcmul(c.unsqueeze(2) * dx, s.unsqueeze(2), dy)  # i to j
    ahead_of_j = torch.addcmul(c.unsqueeze(1) * -dx, s.unsqueeze(1), -dy)  # j to i
    i_yields = (p_i < p_j) | ((p_i == p_j) & (ahead_of_i > ahead_of_j))
    first = (meet & i_yields).any(2)
    second = (meet & ~i_yields).any(1)
    rows = torch.arange(v.x.shape[1], device=v.x.device)
    ego = torch.zeros_like(v.lane[:, 0]) if ego_row is None else ego_row
    stops = (first | second) & v.present & (rows != ego.unsqueeze(1))
    state = torch.where(stops, torch.full_like(state, YIELDING), state)
    return torch.where(stops, torch.zeros_like(target), target), state
