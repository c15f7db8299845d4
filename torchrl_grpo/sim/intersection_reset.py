"""Vehicles arriving and leaving at intersection-v0: spawns, exits, the ego's placement.

``IntersectionEnv`` spawns IDM vehicles at its reset and after every step
(``_spawn_vehicle``), removes those near the end of an exit lane after every step
(``_clear_vehicles``), and places the ego once, after the reset's traffic ran for 3
seconds. These are the pure functions of each; the random draws come in as tensors
(the env package replays highway-env's generator on the host), one spawn per world a
call:

* :func:`spawn_vehicles`: a car on corner ``c``'s incoming lane at
  ``longitudinal + 5 + position_deviation * normal`` m, ``8 + speed_deviation * normal``
  m/s, with its route to ``o<d>`` and its IDM exponent. It is dropped if it lies within
  15 m of any vehicle (highway-env then skips the exponent's draw, so the env needs to
  know: the function returns whether highway-env keeps each car). It takes the first
  free row.
* :func:`clear_vehicles`: removes the IDM vehicles on an exit lane past ``length -
  4 lengths`` and packs the rows again, keeping ``road.vehicles`` order.
* :func:`place_ego`: the ego at ``60 + 5 * normal(1)`` m on the south entry, with its
  route, then removes the IDM vehicles within 20 m of it.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("intersection-v0")
    >>> world = empty_intersection(1, params)
    >>> draws = torch.tensor([[0.1, 1.0, 3.0, 0.0, 0.0, 4.0]], dtype=torch.float64)
    >>> world, stays = spawn_vehicles(world, draws, 0.0, 1.0, 1.0, 0.6, params)
    >>> stays.tolist(), world.vehicles.present[0, :3].tolist(), world.vehicles.speed[0, 1].item()
    ([True], [False, True, False], 8.0)
"""

from __future__ import annotations

import math

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.control import speed_to_index
from torchrl_grpo.sim.intersection_params import IntersectionParams
from torchrl_grpo.sim.roundabout_reset import route_paths
from torchrl_grpo.sim.state import Vehicles, World, empty_world

__all__ = [
    "SPAWN_DRAWS",
    "check_regulated",
    "clear_vehicles",
    "empty_intersection",
    "place_ego",
    "spawn_vehicles",
]

#: A spawn's draws: uniform, corner, destination, position normal, speed normal, exponent.
SPAWN_DRAWS = 6


def empty_intersection(
    batch: int, params: IntersectionParams, dtype=torch.float64, device="cpu"
) -> World:
    """B intersection worlds with no vehicle (the ego's row absent too).

    Example:
        >>> # see the module's example
    """
    world = empty_world(
        batch, params.num_vehicles, dtype, device, params.route_length, regulated=True
    )
    v = world.vehicles
    return world._replace(vehicles=v._replace(present=torch.zeros_like(v.present)))


def _norm_below(v: Vehicles, x, y, radius: float) -> torch.Tensor:
    """``[B, N]``: present rows with ``norm(position - (x, y)) < radius``."""
    dx, dy = v.x - x.unsqueeze(1), v.y - y.unsqueeze(1)
    return v.present & (torch.sqrt(torch.addcmul(dx * dx, dy, dy)) < radius)


def _routes(lane: torch.Tensor, goal: torch.Tensor, params: IntersectionParams) -> torch.Tensor:
    """``[lane] + shortest path to destinations[goal]`` as leg codes ``[..., R]``."""
    road_of = torch.tensor(params.road.road, device=lane.device)
    paths = route_paths(params, lane.device)[road_of[lane], goal]
    return torch.cat([lane.unsqueeze(-1), paths], -1)


def _set_row(world: World, at: torch.Tensor, mask: torch.Tensor, fields: dict) -> World:
    """``world`` with vehicle row ``at[b]`` written from ``fields`` where ``mask``."""
    v = world.vehicles
    n = v.x.shape[1]
    hit = mask.unsqueeze(1) & (torch.arange(n, device=v.x.device) == at.unsqueeze(1))
    table = {
        name: torch.where(hit, fields[name].unsqueeze(1).to(old.dtype), old)
        if name in fields
        else old
        for name, old in v._asdict().items()
    }
    route = torch.where(hit.unsqueeze(-1), fields["route"].unsqueeze(1), world.route)
    return world._replace(
        vehicles=Vehicles(**table),
        route=route,
        route_head=torch.where(hit, 0, world.route_head),
        yielding=torch.where(hit, torch.zeros_like(world.yielding), world.yielding),
    )


def spawn_vehicles(
    world: World,
    draws: torch.Tensor,
    longitudinal: float,
    position_deviation: float,
    speed_deviation: float,
    probability: float,
    params: IntersectionParams,
) -> tuple[World, torch.Tensor]:
    """``_spawn_vehicle`` in every world: ``(worlds, [B] whether highway-env keeps each car)``.

    A car highway-env keeps has its exponent drawn (the env's generator advances by
    one more draw). A world whose table is full (past ``duration``) drops it all the
    same.

    Args:
        world: B intersection worlds.
        draws: ``[B, SPAWN_DRAWS]`` float64: ``uniform()``, the route's corner and
            destination (``choice``), ``normal()`` twice, ``uniform(3.5, 4.5)``.
        longitudinal: the spawn's position before the offset and draw (m).
        position_deviation: the position draw's scale (m).
        speed_deviation: the speed draw's scale (m/s).
        probability: the spawn probability (the reset's first spawns use highway-env's
            default argument, not the config's).
        params: the constants.

    Example:
        >>> # see the module's example
    """
    t, geo = params.traffic, params.road.lanes
    draws = draws.to(world.vehicles.x.device)
    attempt = ~(draws[:, 0] > probability)
    corner, goal = draws[:, 1].to(torch.int64), draws[:, 2].to(torch.int64)
    lane = torch.tensor(t.entry_lanes, device=corner.device)[corner]
    s = (longitudinal + t.spawn_offset) + draws[:, 3] * position_deviation
    x, y = L.position(s, torch.zeros_like(s), lane, geo)
    heading = L.heading_at(s, lane, geo)
    speed = t.spawn_speed + draws[:, 4] * speed_deviation
    v = world.vehicles
    clear = ~_norm_below(v, x, y, t.spawn_clearance).any(1)
    free = ~v.present[:, 1:]
    room = free.any(1)
    stays = attempt & clear & room
    at = 1 + free.to(torch.int8).argmax(1)
    closest = L.closest_lane(x.unsqueeze(1), y.unsqueeze(1), heading.unsqueeze(1), geo).squeeze(1)
    zero = torch.zeros_like(x)
    fields = {
        "x": x, "y": y, "heading": heading, "speed": speed, "target_speed": speed,
        "steering": zero, "acceleration": zero,
        "timer": torch.remainder((x + y) * math.pi, params.idm.lane_change_delay),
        "delta": draws[:, 5], "impact_x": zero, "impact_y": zero, "lane": closest,
        "target_lane": closest, "crashed": ~torch.ones_like(stays),
        "impact": ~torch.ones_like(stays),
        "check_collisions": torch.full_like(stays, t.others_check_collisions),
        "present": torch.ones_like(stays), "route": _routes(closest, goal, params),
    }  # fmt: skip
    return _set_row(world, at, stays, fields), attempt & clear


def _pack(world: World, keep: torch.Tensor) -> World:
    """Drop the rows outside ``keep`` (never row 0) and pack the rest from row 1, in order."""
    v = world.vehicles
    keep = keep & v.present
    first = torch.arange(keep.shape[1], device=keep.device) == 0
    # Row 0 stays the ego's (absent while the reset's traffic runs), then the kept rows.
    key = torch.where(first, 0, torch.where(keep, 1, 2)).to(torch.int8)
    order = torch.argsort(key, dim=1, stable=True)
    removed_before = (~keep[:, 1:] & v.present[:, 1:]).cumsum(1)
    rank = world.ego_rank.clamp(min=1) - 1
    ego_rank = world.ego_rank - torch.where(
        world.ego_rank > 0, removed_before.gather(1, rank.unsqueeze(1)).squeeze(1), 0
    )
    table = Vehicles(*(t.gather(1, order) for t in v))
    table = table._replace(present=keep.gather(1, order))
    route = world.route.gather(1, order.unsqueeze(-1).expand_as(world.route))
    return world._replace(
        vehicles=table,
        route=route,
        route_head=world.route_head.gather(1, order),
        yielding=torch.where(table.present, world.yielding.gather(1, order), 0).to(torch.int8),
        ego_rank=ego_rank,
    )


def clear_vehicles(world: World, params: IntersectionParams) -> World:
    """``_clear_vehicles``: IDM vehicles near an exit lane's end leave; rows packed.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("intersection-v0")
        >>> clear_vehicles(empty_intersection(1, params), params).ego_rank.tolist()
        [0]
    """
    v, geo = world.vehicles, params.road.lanes
    s, _ = L.local_coordinates(v.x, v.y, v.lane, geo)
    exit_lane = torch.tensor(params.road.exit, device=v.x.device)[v.lane]
    length = torch.tensor(geo.length, dtype=v.x.dtype, device=v.x.device)[v.lane]
    leaving = exit_lane & (s >= length - params.traffic.leave_margin)
    leaving[:, 0] = False
    return _pack(world, ~leaving)


def place_ego(
    world: World, rows: torch.Tensor, destination: torch.Tensor, offset: torch.Tensor, params
) -> World:
    """The ego of ``_make_vehicles`` on ``rows``, then the vehicles within 20 m of it removed.

    Args:
        world: B worlds after the reset's spawns and traffic.
        rows: ``[B]`` bool, the worlds to place an ego in.
        destination: ``[B]`` int64 index in ``road.destinations``.
        offset: ``[B]`` float64 ``normal(1.0)``: the ego starts at ``60 + 5 * offset`` m.
        params: the constants.

    Returns:
        The worlds with the ego in row 0, placed after the IDM vehicles in road order.

    Example:
        >>> # see the module's example
    """
    t, geo = params.traffic, params.road.lanes
    device = world.vehicles.x.device
    lane = torch.full_like(destination, t.ego_lane)
    s = t.ego_s + t.ego_scale * offset.to(device)
    x, y = L.position(s, torch.zeros_like(s), lane, geo)
    heading = torch.full_like(s, t.ego_heading)
    closest = L.closest_lane(x.unsqueeze(1), y.unsqueeze(1), heading.unsqueeze(1), geo).squeeze(1)
    speed = torch.full_like(s, t.ego_speed)
    index = speed_to_index(speed, params.control.target_speeds)
    table = torch.tensor(params.control.target_speeds, dtype=s.dtype, device=device)
    zero = torch.zeros_like(s)
    flag = torch.zeros_like(rows)
    fields = {
        "x": x, "y": y, "heading": heading, "speed": speed, "target_speed": table[index],
        "steering": zero, "acceleration": zero, "timer": zero, "delta": zero, "impact_x": zero,
        "impact_y": zero, "lane": closest, "target_lane": closest, "crashed": flag,
        "impact": flag, "check_collisions": ~flag, "present": ~flag,
        "route": _routes(closest, destination.to(device), params),
    }  # fmt: skip
    world = _set_row(world, torch.zeros_like(destination), rows, fields)
    world = world._replace(
        speed_index=torch.where(rows, index, world.speed_index),
        ego_rank=torch.where(rows, world.vehicles.present[:, 1:].sum(1), world.ego_rank),
    )
    near = _norm_below(world.vehicles, x, y, t.ego_clearance) & rows.unsqueeze(1)
    near[:, 0] = False
    return _pack(world, ~near)


def check_regulated(world: World) -> list[str]:
    """The problems of an intersection world's own fields, each naming its entry.

    The rows must be packed (no free row before a vehicle), ``ego_rank`` within the
    vehicles, ``yielding`` a yield state of :mod:`.regulation`, ``road_steps`` not
    negative.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> world = empty_intersection(2, tensor_params("intersection-v0"))
        >>> world.ego_rank[1] = 3
        >>> check_regulated(world)
        ['ego_rank: outside 0 .. the vehicles besides the ego in rows [1]']
    """
    v = world.vehicles
    others = v.present[:, 1:]
    count = others.sum(1)
    rows = torch.arange(others.shape[1], device=others.device)
    problems = []
    for name, bad in (
        ("vehicles.present", (others != (rows < count.unsqueeze(1))).any(1)),
        ("ego_rank", (world.ego_rank < 0) | (world.ego_rank > count)),
        ("yielding", ((world.yielding < 0) | (world.yielding > 2)).any(1)),
        ("road_steps", world.road_steps < 0),
    ):
        if bool(bad.any()):
            why = _WHY[name]
            problems.append(f"{name}: {why} in rows {bad.nonzero().flatten()[:8].tolist()}")
    return problems


_WHY = {
    "vehicles.present": "a free row before a vehicle (rows are packed from row 1)",
    "ego_rank": "outside 0 .. the vehicles besides the ego",
    "yielding": "not a yield state (0, 1 or 2)",
    "road_steps": "negative",
}
