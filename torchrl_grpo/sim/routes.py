"""Route following on a lane graph: ``RoadNetwork.next_lane`` with a planned route, in tensors.

A vehicle's route (``ControlledVehicle.route``) is a row of leg codes ``[R]`` with a
head pointer: legs before the head were dropped (``route.pop(0)``), -1 marks the end.
A leg code is a flat lane id (a leg with a lane, ``(from, to, id)``) below
``road.lanes_count``, or ``lanes_count + road`` (a leg ``(from, to, None)``).

:func:`next_lane` is ``network.next_lane(target, route, position)`` for every vehicle
at once: it drops the head leg if it is the target's road, follows the next leg if it
starts where the target ends, and otherwise scores every road leaving that node by
``next_lane_given_next_road`` (same lane count: the same id; else the closest lane to
the position projected on the target lane's centre) and takes the first closest; with
no road leaving the node the target is kept (highway-env's ``KeyError``).

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> road = tensor_params("roundabout-v0").road
    >>> lane = torch.tensor([[0]])  # (se, ex, 0), at its end, with no route
    >>> x, y = torch.tensor([[18.27]], dtype=torch.float64), torch.tensor([[8.13]]).double()
    >>> route = torch.full((1, 1, road.route_length), -1)
    >>> target, head = next_lane(x, y, lane, route, torch.zeros(1, 1, dtype=torch.int64), road)
    >>> target.tolist()  # the ring's next road, (ex, ee, 0), as highway-env's next_lane
    [[2]]
"""

from __future__ import annotations

import functools

import torch

from torchrl_grpo.sim import lanes as L

__all__ = [
    "RouteFollower",
    "destination_direction",
    "head_leg",
    "leg_lane_id",
    "leg_road",
    "next_lane",
    "road_tables",
]


@functools.lru_cache(maxsize=64)
def road_tables(road, device: torch.device) -> dict[str, torch.Tensor]:
    """A routed road's lookup tables on ``device`` (cached): per lane and per road.

    ``road`` / ``id`` per leg code; ``lane_road``, ``lane_id`` per lane; ``from``,
    ``to``, ``lanes`` (``[roads, W]``, -1 padded), ``count`` and ``next`` per road.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road_tables(tensor_params("roundabout-v0").road, torch.device("cpu"))["lanes"].shape
        torch.Size([24, 2])
    """

    def t(values) -> torch.Tensor:
        return torch.tensor(values, dtype=torch.int64, device=device)

    lane_road = t(road.road)
    return {
        # Per code: its road, and its lane id (-1: none chosen).
        "road": torch.cat([lane_road, torch.arange(road.roads_count, device=device)]),
        "id": torch.cat([t(road.lane_id), torch.full((road.roads_count,), -1, device=device)]),
        "lane_road": lane_road,
        "lane_id": t(road.lane_id),
        "from": t(road.road_from),
        "to": t(road.road_to),
        "lanes": t(road.road_lanes),
        "count": (t(road.road_lanes) >= 0).sum(-1),
        "next": t(road.next_roads),
    }


def head_leg(route: torch.Tensor, head: torch.Tensor) -> torch.Tensor:
    """The leg code at each route's head (-1 where the route is used up).

    Example:
        >>> head_leg(torch.tensor([[[4, 7, -1]]]), torch.tensor([[1]])).tolist()
        [[7]]
    """
    length = route.shape[-1]
    leg = route.gather(-1, head.clamp(max=length - 1).unsqueeze(-1)).squeeze(-1)
    return torch.where(head < length, leg, -1)


def leg_road(leg: torch.Tensor, road) -> torch.Tensor:
    """The road of each leg code (-1 for -1).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> leg_road(torch.tensor([0, 1, 32, -1]), tensor_params("roundabout-v0").road).tolist()
        [0, 0, 0, -1]
    """
    table = road_tables(road, leg.device)["road"]
    return torch.where(leg >= 0, table[leg.clamp(min=0)], -1)


def leg_lane_id(leg: torch.Tensor, road) -> torch.Tensor:
    """The lane id a leg names, -1 where it names none (``None``) or for -1.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> leg_lane_id(torch.tensor([1, 32, -1]), tensor_params("roundabout-v0").road).tolist()
        [1, -1, -1]
    """
    table = road_tables(road, leg.device)["id"]
    return torch.where(leg >= 0, table[leg.clamp(min=0)], -1)


def destination_direction(
    x: torch.Tensor, y: torch.Tensor, route: torch.Tensor, head: torch.Tensor, road
) -> tuple[torch.Tensor, torch.Tensor]:
    """``Vehicle.destination_direction`` of every vehicle: the unit vector to its route's end.

    The end is the last leg's lane (lane 0 of a leg ``(from, to, None)``) at its length.
    The direction is zero where the route is used up (``route == []``: highway-env's
    destination is then the position) or the vehicle stands on its end.

    Args:
        x: ``[B, N]`` positions.
        y: see ``x``.
        route: ``[B, N, R]`` leg codes.
        head: ``[B, N]`` each route's head.
        road: the road graph (a routed road).

    Returns:
        ``(cos_d, sin_d)``, both ``[B, N]`` in ``x``'s dtype.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("roundabout-v0").road
        >>> x, y = torch.tensor([[2.0, 2.0]]).double(), torch.tensor([[45.0, 45.0]]).double()
        >>> route = torch.tensor([[[0, -1], [0, -1]]])  # one leg: (se, ex, 0)
        >>> cos_d, sin_d = destination_direction(x, y, route, torch.tensor([[0, 1]]), road)
        >>> [round(v, 4) for v in cos_d[0].tolist()], [round(v, 4) for v in sin_d[0].tolist()]
        ([0.4038, 0.0], [-0.9149, 0.0])
    """
    tab = road_tables(road, x.device)
    count = (route >= 0).sum(-1)
    last = route.gather(-1, (count - 1).clamp(min=0).unsqueeze(-1)).squeeze(-1)
    lane_id = leg_lane_id(last, road).clamp(min=0)
    lane = tab["lanes"][leg_road(last, road).clamp(min=0), lane_id]
    length = torch.tensor(road.lanes.length, dtype=x.dtype, device=x.device)[lane]
    end_x, end_y = L.position(length, torch.zeros_like(length), lane, road.lanes)
    dx, dy = end_x - x, end_y - y
    moving = (head < count) & ((dx != 0) | (dy != 0))
    # np.linalg.norm of a 2-vector: sqrt(fma(dy, dy, dx * dx)).
    norm = torch.where(moving, torch.sqrt(torch.addcmul(dx * dx, dy, dy)), torch.ones_like(dx))
    zero = torch.zeros_like(dx)
    return torch.where(moving, dx / norm, zero), torch.where(moving, dy / norm, zero)


def next_lane(
    x: torch.Tensor,
    y: torch.Tensor,
    target: torch.Tensor,
    route: torch.Tensor,
    head: torch.Tensor,
    road,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``network.next_lane(target, route, position)`` of every vehicle, and the routes' heads.

    Args:
        x: ``[B, K]`` positions.
        y: see ``x``.
        target: ``[B, K]`` the lanes being left (flat ids).
        route: ``[B, K, R]`` leg codes.
        head: ``[B, K]`` each route's head.
        road: the road graph (a :class:`~.roundabout_params.RoundaboutRoad`).

    Returns:
        ``(next lanes, heads after dropping a finished leg)``, both ``[B, K]``.

    Example:
        >>> # see the module's example
    """
    geo, tab = road.lanes, road_tables(road, x.device)
    current = tab["lane_road"][target]
    end = tab["to"][current]
    leg = head_leg(route, head)
    finished = (leg >= 0) & (leg_road(leg, road) == current)
    head = head + finished.to(head.dtype)
    leg = head_leg(route, head)
    leg_to = leg_road(leg, road)
    follows = (leg >= 0) & (tab["from"][leg_to.clamp(min=0)] == end)
    chosen_id = torch.where(follows, leg_lane_id(leg, road), -1)
    # Candidate roads: the route's next one, or every road leaving the end node.
    leaving = tab["next"][current]  # [B, K, C]
    candidates = torch.where(
        follows.unsqueeze(-1),
        torch.cat([leg_to.unsqueeze(-1), torch.full_like(leaving[..., 1:], -1)], -1),
        leaving,
    )
    s, _ = L.local_coordinates(x, y, target, geo)
    px, py = L.position(s, torch.zeros_like(s), target, geo)
    px, py = px.unsqueeze(-1), py.unsqueeze(-1)
    valid = candidates >= 0
    cand = candidates.clamp(min=0)
    lanes = tab["lanes"][cand]  # [B, K, C, W]
    same = tab["count"][cand] == tab["count"][current].unsqueeze(-1)
    own_id = tab["lane_id"][target].unsqueeze(-1)
    same_id = torch.where(chosen_id.unsqueeze(-1) >= 0, chosen_id.unsqueeze(-1), own_id)
    # Same lane count: the named (or the same) id; else the first closest lane of the road.
    per_lane = L.lane_distance(
        px.unsqueeze(-1), py.unsqueeze(-1), lanes.clamp(min=0), geo
    ).masked_fill(lanes < 0, float("inf"))
    closest = per_lane.argmin(-1, keepdim=True)
    same_lane = lanes.gather(-1, same_id.clamp(max=lanes.shape[-1] - 1).unsqueeze(-1))
    pick = torch.where(same.unsqueeze(-1), same_lane, lanes.gather(-1, closest)).squeeze(-1)
    distance = L.lane_distance(px, py, pick.clamp(min=0), geo)
    distance = distance.masked_fill(~valid, float("inf"))
    best = distance.argmin(-1, keepdim=True)
    nxt = pick.gather(-1, best).squeeze(-1)
    return torch.where(valid.any(-1), nxt, target), head


class RouteFollower:
    """The routes during one substep: ``follow_road`` drops finished legs as it goes.

    Args:
        world: worlds with routes (``route``, ``route_head``).
        params: a routed scenario's constants (``params.road`` a routed road).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> from torchrl_grpo.sim.state import empty_world
        >>> params = tensor_params("roundabout-v0")
        >>> world = empty_world(1, 2, torch.float64, route_length=params.route_length)
        >>> follower = RouteFollower(world, params)
        >>> follower.head is world.route_head  # a copy: the world is not changed
        False
    """

    def __init__(self, world, params) -> None:
        self.route, self.head, self.params = world.route, world.route_head.clone(), params

    def follow(self, rows: slice, x, y, target, mask) -> torch.Tensor:
        """``follow_road`` of the vehicles ``rows`` where ``mask`` holds (see merge's)."""
        road = self.params.road
        s, _ = L.local_coordinates(x, y, target, road.lanes)
        due = mask & L.after_end(s, target, road.lanes)
        if not bool(due.any()):
            return target
        heads = self.head[:, rows]
        nxt, moved = next_lane(x, y, target, self.route[:, rows], heads, road)
        self.head[:, rows] = torch.where(due, moved, heads)
        return torch.where(due, nxt, target)

    def wanted_id(self, rows: slice) -> torch.Tensor:
        """The lane id each route's head leg names (-1: none, the plain MOBIL test)."""
        leg = head_leg(self.route[:, rows], self.head[:, rows])
        return leg_lane_id(leg, self.params.road)
