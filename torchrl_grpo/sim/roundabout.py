"""One env step of B roundabout-v0 worlds: the ring, its entries and exits, routes.

The substep is merge-v0's (:mod:`.merge`: the ego's meta-action and ``follow_road``,
the IDM vehicles in road order with the abort scan, MOBIL and IDM along each one's
current lane, the bicycle model, the closest lane over the 32 lanes, every pair's
collision), with what the roundabout adds:

* ``follow_road`` follows each vehicle's planned route (:func:`.routes.next_lane`):
  at the end of its target lane the finished leg is dropped and the next leg's road
  taken, its lane the same id on the ring or the closest one where the lane count
  changes (entries and exits); the head pointers of the routes advance in the state;
* MOBIL's route rule: while a route's head leg names a lane (the spawn lane, until it
  is dropped), a candidate lane passes only if it lies on the side of that lane and is
  safe for both the new follower and the vehicle itself, without the incentive test;
* no obstacle: every row is a vehicle.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.roundabout_reset import DRAWS, reset_roundabout
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("roundabout-v0")
    >>> world = empty_world(2, params.num_vehicles, torch.float64, route_length=params.route_length)
    >>> draws = torch.zeros(2, DRAWS, dtype=torch.float64)
    >>> draws[:, 3::4] = 4.0  # every IDM exponent 4
    >>> world = reset_roundabout(world, torch.ones(2, dtype=torch.bool), draws, params)
    >>> world, out = roundabout_step(world, torch.tensor([1, 3]), params)
    >>> world.steps.tolist(), out["observation"].shape
    ([15, 15], torch.Size([2, 5, 5]))
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.collision import collide
from torchrl_grpo.sim.kinematics import step_vehicles
from torchrl_grpo.sim.merge import _ego_act, _Others, _others_act
from torchrl_grpo.sim.roundabout_output import observe_roundabout
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.routes import RouteFollower
from torchrl_grpo.sim.state import World

__all__ = ["act_on_routes", "roundabout_step", "roundabout_substep"]


class _RoutedOthers(_Others):
    """The IDM vehicles deciding with MOBIL's route rule (``IDMVehicle.mobil``)."""

    def __init__(self, v, params: RoundaboutParams, routes: RouteFollower) -> None:
        super().__init__(v, params)
        self.routes = routes

    def mobil(self, candidate, acc_now, free, target) -> torch.Tensor:
        idm = self.params.idm
        unsafe, mine = self.mobil_parts(candidate, free)
        jerk = mine - acc_now
        plain = ~unsafe & ~(jerk < idm.lane_change_min_acc_gain)
        wanted = self.routes.wanted_id(slice(1, self.params.obstacle_row))
        ids = torch.tensor(self.params.road.lane_id, device=candidate.device)
        now = ids[target]
        side = torch.sign(ids[candidate] - now) == torch.sign(wanted - now)
        routed = ~unsafe & side & ~(mine < -idm.lane_change_max_braking_imposed)
        return torch.where(wanted >= 0, routed, plain)


def act_on_routes(world: World, action: torch.Tensor, params) -> tuple:
    """Every vehicle's ``act()`` of a frame on routed roads (the roundabout's, the intersection's).

    ``action`` (meta-actions, -1: none) applies where ``steps`` is a multiple of
    ``frames``. Returns ``(vehicles, decided, speed_index, routes)``: the table with the
    ego's new target speed, the decided columns (target lanes, target speeds, commands,
    timers) to step it with, the ego's speed index, and the routes with their new heads.

    Example:
        >>> # see the module's example
    """
    v = world.vehicles
    first = torch.remainder(world.steps, params.time.frames) == 0
    action = torch.where(first, action, torch.full_like(action, -1))
    cols = {
        k: getattr(v, k).clone()
        for k in ("target_lane", "target_speed", "steering", "acceleration", "timer")
    }
    routes = RouteFollower(world, params)
    index = _ego_act(v, world.speed_index, action, first, cols, params, routes.follow)
    v = v._replace(target_speed=cols["target_speed"])
    _others_act(v, cols, params, routes.follow, lambda v_, p: _RoutedOthers(v_, p, routes))
    return v, cols, index, routes


def roundabout_substep(world: World, action: torch.Tensor, params: RoundaboutParams) -> World:
    """One simulation frame; ``action`` applies where ``steps`` is a multiple of ``frames``.

    Example:
        >>> # see the module's example
    """
    v, cols, index, routes = act_on_routes(world, action, params)
    moved = step_vehicles(
        v._replace(**cols),
        params,
        closest=lambda x, y, h: L.closest_lane(x, y, h, params.road.lanes),
    )
    moved = collide(moved, params)
    return world._replace(
        vehicles=moved, speed_index=index, steps=world.steps + 1, route_head=routes.head
    )


def roundabout_step(
    world: World, action: torch.Tensor, params: RoundaboutParams
) -> tuple[World, dict]:
    """``env.step(action)`` for B roundabout worlds.

    Args:
        world: B worlds with their routes.
        action: ``[B]`` int64 meta-actions.
        params: the constants.

    Returns:
        ``(worlds after the step, observe_roundabout of them with this action's reward)``.

    Example:
        >>> # see the module's example
    """
    world = world._replace(time=world.time + params.time.step_time)
    for _ in range(params.time.frames):
        world = roundabout_substep(world, action, params)
    return world, observe_roundabout(world, params, action)
