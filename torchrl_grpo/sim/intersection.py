"""One env step of B intersection-v0 worlds: routes, right of way, vehicles coming and going.

A frame is roundabout-v0's (:func:`.roundabout.act_on_routes`: the ego's meta-action
and ``follow_road`` along its route, the IDM vehicles along theirs; then every
vehicle's motion, the closest lane, every pair's collision), with what
``RegulatedRoad`` and ``IntersectionEnv`` add:

* the ego's actions are longitudinal only: 0 SLOWER, 1 IDLE, 2 FASTER;
* every road has one lane, so no IDM vehicle changes lanes (MOBIL finds no candidate);
* after the vehicles decide and before they move, every ``regulation.every`` road
  frames, the right-of-way pass (:func:`.regulation.enforce_road_rules`);
* collisions are checked in ``road.vehicles`` order, where the ego comes after the
  reset's vehicles and before later spawns (``ego_rank``);
* after the step's frames and its outputs, the vehicles near an exit's end leave and
  one spawn is attempted (:mod:`.intersection_reset`), from the step's draws.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.intersection_reset import SPAWN_DRAWS, empty_intersection, place_ego
    >>> params = tensor_params("intersection-v0")
    >>> world = empty_intersection(2, params)
    >>> one = torch.ones(2, dtype=torch.bool)
    >>> world = place_ego(world, one, torch.tensor([1, 2]), torch.ones(2).double(), params)
    >>> no_spawn = torch.ones(2, SPAWN_DRAWS, dtype=torch.float64)  # uniform() = 1 > 0.6
    >>> world, out, stays = intersection_step(world, torch.tensor([2, 0]), no_spawn, params)
    >>> world.steps.tolist(), out["observation"].shape, stays.tolist()
    ([15, 15], torch.Size([2, 15, 7]), [False, False])
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.collision import collide
from torchrl_grpo.sim.control import FASTER, IDLE, SLOWER
from torchrl_grpo.sim.intersection_output import observe_intersection
from torchrl_grpo.sim.intersection_params import IntersectionParams
from torchrl_grpo.sim.intersection_reset import clear_vehicles, spawn_vehicles
from torchrl_grpo.sim.kinematics import step_vehicles
from torchrl_grpo.sim.regulation import enforce_road_rules
from torchrl_grpo.sim.roundabout import act_on_routes
from torchrl_grpo.sim.state import Vehicles, World, map_world

__all__ = [
    "INTERSECTION_ACTIONS",
    "FramesFn",
    "intersection_step",
    "intersection_substep",
    "road_order",
    "tensor_frames",
    "warm_up",
]

#: ``(world, meta-actions, frames, params) -> world``: a number of frames of B worlds
#: (:func:`tensor_frames`, or the C++ ones: :func:`.intersection_native.native_frames`).
FramesFn = Callable[[World, torch.Tensor, int, IntersectionParams], World]

#: The meta-action of each of intersection-v0's actions (SLOWER, IDLE, FASTER).
INTERSECTION_ACTIONS = (SLOWER, IDLE, FASTER)


def road_order(ego_rank: torch.Tensor, n: int) -> torch.Tensor:
    """``[B, N]``: the table's rows in ``road.vehicles`` order (the ego after ``ego_rank``).

    Example:
        >>> road_order(torch.tensor([2]), 5).tolist()  # two cars, the ego, then the rest
        [[1, 2, 0, 3, 4]]
    """
    k = torch.arange(n, device=ego_rank.device).expand(ego_rank.shape[0], n)
    rank = ego_rank.unsqueeze(1)
    return torch.where(k < rank, k + 1, torch.where(k == rank, 0, k))


def _permute(t: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """Rows of a ``[B, N, ...]`` tensor in ``order``."""
    index = order.reshape(*order.shape, *([1] * (t.ndim - 2))).expand_as(t)
    return t.gather(1, index)


def _in_road_order(fn, order: torch.Tensor, back: torch.Tensor, v: Vehicles, *tables):
    """``fn(v, *tables)`` on the rows in ``road.vehicles`` order (``order``), put back (``back``).

    Pairs are visited in that order, and it decides ties: the earlier vehicle's impact
    is overwritten by a later pair's, the later vehicle yields at equal distances.
    """
    out = fn(Vehicles(*(_permute(t, order) for t in v)), *(_permute(t, order) for t in tables))
    if isinstance(out, Vehicles):
        return Vehicles(*(_permute(t, back) for t in out))
    return tuple(_permute(t, back) for t in out)


def intersection_substep(world: World, action: torch.Tensor, params: IntersectionParams) -> World:
    """One simulation frame; ``action`` (meta-actions, -1: none) applies on a step's first frame.

    Example:
        >>> # see the module's example
    """
    v, cols, index, routes = act_on_routes(world, action, params)
    road_steps = world.road_steps + 1
    due = torch.remainder(road_steps, params.regulation.every) == 0
    yielding = world.yielding
    ego_row = world.ego_rank
    order = road_order(ego_row, v.x.shape[1])
    back = torch.argsort(order, dim=1)
    if bool(due.any()):
        decided = v._replace(target_lane=cols["target_lane"])
        speed, flags = _in_road_order(
            lambda *a: enforce_road_rules(*a, params, ego_row=ego_row),
            order,
            back,
            decided,
            world.route,
            routes.head,
            yielding,
        )
        cols["target_speed"] = torch.where(due.unsqueeze(1), speed, cols["target_speed"])
        yielding = torch.where(due.unsqueeze(1), flags, yielding)
    moved = step_vehicles(
        v._replace(**cols),
        params,
        closest=lambda x, y, h: L.closest_lane(x, y, h, params.road.lanes),
    )
    moved = _in_road_order(lambda t: collide(t, params), order, back, moved)
    return world._replace(
        vehicles=moved,
        speed_index=index,
        steps=world.steps + 1,
        route_head=routes.head,
        yielding=yielding,
        road_steps=road_steps,
    )


@functools.lru_cache(maxsize=64)
def _narrowed(params: IntersectionParams, rows: int) -> IntersectionParams:
    """``params`` for a table of ``rows`` rows (the ego and ``rows - 1`` others)."""
    return dataclasses.replace(
        params, traffic=dataclasses.replace(params.traffic, max_vehicles=rows - 1)
    )


def tensor_frames(world: World, action: torch.Tensor, frames: int, params) -> World:
    """``frames`` substeps on the rows in use, the free rows after them set aside.

    The rows are packed, so the first ``1 + max(others)`` hold every vehicle of every
    world: the pair computations (neighbours, conflicts, collisions) shrink with the
    square of the rows, and a free row changes no present one's result.

    Example:
        >>> # see the module's example
    """
    used = 1 + int(world.vehicles.present[:, 1:].sum(1).max())
    if used == world.vehicles.x.shape[1]:
        for _ in range(frames):
            world = intersection_substep(world, action, params)
        return world
    part = map_world(lambda t: t[:, :used] if t.ndim > 1 else t, world)
    narrow = _narrowed(params, used)
    for _ in range(frames):
        part = intersection_substep(part, action, narrow)

    def put_back(full: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        return torch.cat([new, full[:, used:]], 1) if full.ndim > 1 else new

    return map_world(put_back, world, part)


def warm_up(
    world: World, rows: torch.Tensor, params: IntersectionParams, frames: FramesFn = tensor_frames
) -> World:
    """The reset's 3 seconds of traffic on ``rows``, before the ego exists (the others kept).

    ``frames`` runs them (the tensor path's by default).

    Example:
        >>> # see the module's example
    """
    index = rows.nonzero().flatten()
    if index.numel() == 0:
        return world
    sub = map_world(lambda t: t.index_select(0, index), world)
    no_action = torch.full_like(sub.steps, -1)
    sub = frames(sub, no_action, params.traffic.warmup_frames, params)
    sub = sub._replace(steps=world.steps.index_select(0, index))
    return map_world(lambda t, s: t.index_copy(0, index, s), world, sub)


def intersection_step(
    world: World,
    action: torch.Tensor,
    draws: torch.Tensor,
    params: IntersectionParams,
    frames: FramesFn = tensor_frames,
) -> tuple[World, dict, torch.Tensor]:
    """``env.step(action)`` for B intersection worlds.

    Args:
        world: B worlds.
        action: ``[B]`` int64 actions of intersection-v0 (0 SLOWER, 1 IDLE, 2 FASTER).
        draws: ``[B, SPAWN_DRAWS]`` the step's spawn draws (see
            :func:`~.intersection_reset.spawn_vehicles`).
        params: the constants.
        frames: runs the step's frames (:func:`tensor_frames`, or the C++ ones).

    Returns:
        ``(worlds after the step, observe_intersection of them before the exits and
        the spawn, [B] whether highway-env keeps the spawned car)``.

    Example:
        >>> # see the module's example
    """
    meta = torch.tensor(INTERSECTION_ACTIONS, device=action.device)[action]
    world = world._replace(time=world.time + params.time.step_time)
    world = frames(world, meta, params.time.frames, params)
    out = observe_intersection(world, params)
    world = clear_vehicles(world, params)
    t = params.traffic
    world, stays = spawn_vehicles(
        world, draws, 0.0, t.position_deviation, t.speed_deviation, t.spawn_probability, params
    )
    return world, out, stays
