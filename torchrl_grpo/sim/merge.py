"""One env step of B merge-v0 worlds: the ramp, its joints, the obstacle, MOBIL across roads.

A substep is ``AbstractEnv._simulate``'s frame, as for the highway (:mod:`.simulate`),
on the merge road's lane graph (:mod:`.lanes`):

1. the ego (row 0): ``follow_road`` (past ``after_end`` of its target lane, the target
   becomes ``next_lane``), then on an env step's first frame its meta-action (a lane
   change is refused unless the lane ``clip(id -/+ 1)`` of the target's road is
   reachable: the ramp's lanes are forbidden) and ``follow_road`` again, then the
   steering cascade towards its target lane and the speed controller;
2. the IDM vehicles, one after the other in road order (each reads the targets the
   earlier ones just wrote, as ``road.act`` does): ``follow_road``, the lane-change
   policy (the abort scan while changing on the same road, nothing during a
   hand-over between roads, else MOBIL on ``side_lanes`` every second), steering, and
   IDM behind the front vehicle of the current lane (and of the target lane while
   changing), with the lane speed limit capping target speeds;
3. every vehicle moves; the closest lane is searched over the 9 lanes; pairs of
   vehicles collide, then each vehicle with the obstacle (the last row), whose
   impact replaces any other (full translation, not half).

Distances along a lane are ``lane_distance_to``: both positions' longitudinal
coordinates in the DECIDING vehicle's current lane. The front and rear vehicles of a
lane are ``Road.neighbour_vehicles``': every vehicle and the obstacle within
``width / 2 + 1`` of that lane, ranked by their coordinate along it.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.merge_reset import reset_merge
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("merge-v0")
    >>> world = empty_world(2, params.num_vehicles, torch.float64)
    >>> draws = torch.tensor([[1.0, 0, 0, 0, 0, 0, 1.0, 0, 0]] * 2, dtype=torch.float64)
    >>> world = reset_merge(world, torch.ones(2, dtype=torch.bool), draws, params)
    >>> world, out = merge_step(world, torch.tensor([1, 3]), params)
    >>> world.steps.tolist(), out["observation"].shape
    ([15, 15], torch.Size([2, 5, 5]))
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.collision import _all_pairs, _reach, separating_axes
from torchrl_grpo.sim.control import FASTER, LANE_LEFT, LANE_RIGHT, SLOWER, speed_to_index, steer_to
from torchrl_grpo.sim.idm import Car, desired_gap, free_road, interaction
from torchrl_grpo.sim.kinematics import step_vehicles
from torchrl_grpo.sim.merge_output import observe_merge
from torchrl_grpo.sim.merge_params import MergeParams
from torchrl_grpo.sim.state import Vehicles, World

__all__ = ["merge_step", "merge_substep"]


def _const(values: tuple, like: torch.Tensor) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.int64, device=like.device)


def _follow_road(x, y, target, params: MergeParams) -> torch.Tensor:
    """``ControlledVehicle.follow_road``: past its target lane's end, hand over to the next."""
    geo = params.road.lanes
    s, _ = L.local_coordinates(x, y, target, geo)
    return torch.where(
        L.after_end(s, target, geo), _const(params.road.next_lane, x)[target], target
    )


def _steer(x, y, speed, heading, target, params: MergeParams) -> torch.Tensor:
    """``steering_control(target)`` on any lane of the graph."""
    geo = params.road.lanes
    s, r = L.local_coordinates(x, y, target, geo)
    future = L.heading_at(s + speed * params.control.tau_pursuit, target, geo)
    return steer_to(r, future, speed, heading, params)


class _Scene:
    """What a substep's decisions read and no decision changes: positions, speeds, targets."""

    def __init__(self, v: Vehicles, params: MergeParams) -> None:
        self.v, self.params = v, params
        self.cos, self.sin = torch.cos(v.heading), torch.sin(v.heading)
        # The obstacle is found as a front vehicle, but is no Vehicle as a follower.
        self.is_vehicle = torch.ones_like(v.present)
        self.is_vehicle[:, params.obstacle_row] = False

    def along(self, lane: torch.Tensor) -> torch.Tensor:
        """``[B, N]``: every row's longitudinal coordinate in lane ``lane`` (``[B]``)."""
        v = self.v
        return L.local_coordinates(v.x, v.y, lane.unsqueeze(1), self.params.road.lanes)[0]

    def car(self, at: torch.Tensor, s: torch.Tensor, exists: torch.Tensor | None = None) -> Car:
        """The :class:`~.idm.Car` of row ``at`` (``[B]``, clamped), placed at ``s`` along a lane."""
        v, i = self.v, at.clamp(min=0).unsqueeze(1)
        pick = lambda t: t.gather(1, i).squeeze(1)  # noqa: E731
        return Car(s, pick(v.speed), pick(self.cos), pick(self.sin), pick(v.target_speed), exists)

    def neighbours(self, me: int, lane: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``Road.neighbour_vehicles(vehicle me, lane)``: front and rear rows (-1: none)."""
        v, geo = self.v, self.params.road.lanes
        s, r = L.local_coordinates(v.x, v.y, lane.unsqueeze(1), geo)
        member = L.on_lane(s, r, lane.unsqueeze(1), geo, margin=1.0) & v.present
        member[:, me] = False
        mine = s[:, me : me + 1]
        inf = torch.full_like(s, float("inf"))
        ahead = torch.where(member & (mine <= s), s, inf)
        n = s.shape[1]
        # Ties: the later row in front (``s_v <= s_front``), the first behind (``s_v > s_rear``).
        front = (n - 1) - ahead.flip(-1).argmin(-1)
        front = torch.where(ahead.amin(-1) < float("inf"), front, -1)
        behind = torch.where(member & (s < mine), s, -inf)
        rear = torch.where(behind.amax(-1) > -float("inf"), behind.argmax(-1), -1)
        return front, rear

    def idm(self, me: int, front: torch.Tensor, s_mine: torch.Tensor, delta, free) -> torch.Tensor:
        """``acceleration(me, front)`` with ``s_mine`` the rows' coordinates in me's lane."""
        pick = lambda t, i: t.gather(1, i.clamp(min=0).unsqueeze(1)).squeeze(1)  # noqa: E731
        ego = self.car(torch.full_like(front, me), s_mine[:, me])
        ahead = self.car(front, pick(s_mine, front), exists=front >= 0)
        return free - interaction(ego, ahead, self.params)


def _mobil(scene: _Scene, me: int, candidate, s_mine, acc_now, free) -> torch.Tensor:
    """``IDMVehicle.mobil(candidate)`` of row ``me`` (route-less: the plain MOBIL test)."""
    v, params, idm = scene.v, scene.params, scene.params.idm
    new_front, new_rear = scene.neighbours(me, candidate)
    delta = v.delta[:, me]
    # The new follower brakes for me, measured in ITS current lane, with MY exponent.
    rear_lane = v.lane.gather(1, new_rear.clamp(min=0).unsqueeze(1)).squeeze(1)
    s_rear = scene.along(rear_lane)
    exists = (new_rear >= 0) & scene.is_vehicle.gather(
        1, new_rear.clamp(min=0).unsqueeze(1)
    ).squeeze(1)
    follower = scene.car(
        new_rear, s_rear.gather(1, new_rear.clamp(min=0).unsqueeze(1)).squeeze(1), exists
    )
    me_there = scene.car(torch.full_like(new_rear, me), s_rear[:, me])
    pred = free_road(follower, delta, params) - interaction(follower, me_there, params)
    unsafe = pred < -idm.lane_change_max_braking_imposed
    self_pred = scene.idm(me, new_front, s_mine, delta, free)
    # Politeness is 0 in highway-env; merge_config refuses other values.
    jerk = self_pred - acc_now
    return ~unsafe & ~(jerk < idm.lane_change_min_acc_gain)


def _idm_act(v: Vehicles, scene: _Scene, me: int, cols: dict, params: MergeParams) -> None:
    """``IDMVehicle.act`` of row ``me``, writing its target, timer and commands into ``cols``."""
    road, geo, idm = params.road, params.road.lanes, params.idm
    x, y, speed = v.x[:, me], v.y[:, me], v.speed[:, me]
    acting = ~v.crashed[:, me]
    lane = v.lane[:, me]
    target = _follow_road(x, y, cols["target_lane"][:, me], params)
    road_of = _const(road.road, x)
    changing = lane != target
    s_mine = scene.along(lane)
    # The abort scan: someone else heads for my target lane, ahead of me within my gap.
    others = cols["target_lane"]
    me_car = scene.car(torch.full_like(lane, me), s_mine[:, me])
    gap = desired_gap(
        Car(*(t.unsqueeze(1) for t in me_car[:5])),
        Car(s_mine, v.speed, scene.cos, scene.sin, v.target_speed),
        params,
    )
    d = s_mine - s_mine[:, me : me + 1]
    rows = scene.is_vehicle & (torch.arange(v.x.shape[1], device=x.device) != me)
    heading_there = rows & (v.lane != target.unsqueeze(1)) & (others == target.unsqueeze(1))
    blocked = (heading_there & (0 < d) & (d < gap)).any(-1)
    abort = changing & (road_of[lane] == road_of[target]) & blocked
    target = torch.where(abort, lane, target)
    # MOBIL, every lane_change_delay seconds, while not changing lanes.
    free = free_road(me_car, v.delta[:, me], params)
    front, _ = scene.neighbours(me, lane)
    acc = scene.idm(me, front, s_mine, v.delta[:, me], free)
    due = ~changing & (idm.lane_change_delay < cols["timer"][:, me])
    timer = torch.where(due, torch.zeros_like(x), cols["timer"][:, me])
    if bool(due.any()):
        moving = ~(speed.abs() < 1)
        for side in (road.side_left, road.side_right):  # left, then right: right wins
            candidate = _const(side, x)[lane]
            exists = candidate >= 0
            candidate = candidate.clamp(min=0)
            s_c, r_c = L.local_coordinates(x, y, candidate, geo)
            ok = due & exists & moving & L.is_reachable(s_c, r_c, candidate, geo)
            if bool(ok.any()):
                ok = ok & _mobil(scene, me, candidate, s_mine, acc, free)
                target = torch.where(ok, candidate, target)
    steer = _steer(x, y, speed, v.heading[:, me], target, params)
    target_front, _ = scene.neighbours(me, target)
    acc_target = scene.idm(me, target_front, s_mine, v.delta[:, me], free)
    acc = torch.where(lane != target, torch.minimum(acc, acc_target), acc)
    acc = torch.clamp(acc, -idm.acc_max, idm.acc_max)
    for name, value in (
        ("target_lane", target),
        ("timer", timer),
        ("steering", steer),
        ("acceleration", acc),
    ):
        cols[name][:, me] = torch.where(acting, value, cols[name][:, me])


def _ego_act(v: Vehicles, index, action, first, cols: dict, params: MergeParams):
    """The MDP ego's ``act(action)`` (first frame) and ``act()``: target lane, speed, commands."""
    geo, speeds = params.road.lanes, params.control.target_speeds
    x, y, speed = v.x[:, 0], v.y[:, 0], v.speed[:, 0]
    target = _follow_road(x, y, v.target_lane[:, 0], params)
    left, right = _const(params.road.left, x)[target], _const(params.road.right, x)[target]
    candidate = torch.where(action == LANE_LEFT, left, right)
    s, r = L.local_coordinates(x, y, candidate, geo)
    change = ((action == LANE_LEFT) | (action == LANE_RIGHT)) & L.is_reachable(s, r, candidate, geo)
    target = torch.where(change, candidate, target)
    step = torch.where(action == FASTER, 1, torch.where(action == SLOWER, -1, 0))
    moved = torch.clamp(speed_to_index(speed, speeds) + step, 0, len(speeds) - 1)
    index = torch.where(step != 0, moved, index)
    table = torch.tensor(speeds, dtype=speed.dtype, device=speed.device)
    target_speed = torch.where(step != 0, table[moved], v.target_speed[:, 0])
    target = torch.where(first, _follow_road(x, y, target, params), target)
    cols["target_lane"][:, 0] = target
    cols["target_speed"][:, 0] = target_speed
    cols["steering"][:, 0] = _steer(x, y, speed, v.heading[:, 0], target, params)
    cols["acceleration"][:, 0] = params.control.kp_a * (target_speed - speed)
    return index


def _collide(v: Vehicles, params: MergeParams) -> Vehicles:
    """Vehicle pairs as on the highway, then each vehicle with the obstacle (last row)."""
    o = params.obstacle_row
    cars = Vehicles(*(t[:, :o] for t in v))
    cars = _all_pairs(cars, params)
    ox, oy = v.x[:, o : o + 1], v.y[:, o : o + 1]
    traffic = params.traffic
    dx, dy = ox - cars.x, oy - cars.y
    diagonal = (traffic.obstacle_length**2 + traffic.obstacle_width**2) ** 0.5
    reach = _reach(cars.speed, params) - (_reach(cars.speed * 0, params)) / 2
    reach = reach + diagonal / 2
    near = ~(torch.sqrt(torch.addcmul(dx * dx, dy, dy)) > reach)
    near = near & (cars.check_collisions | v.check_collisions[:, o : o + 1])
    hit = torch.zeros_like(near)
    will = torch.zeros_like(near)
    tx, ty = torch.zeros_like(dx), torch.zeros_like(dx)
    if bool(near.any()):
        a = (cars.x, cars.y, cars.heading, cars.speed)
        b = tuple(t[:, o : o + 1].expand_as(cars.x) for t in (v.x, v.y, v.heading, v.speed))
        size = (traffic.obstacle_length, traffic.obstacle_width)
        h, w, x_, y_ = separating_axes(
            a, b, params.time.dt, params.vehicle.length, params.vehicle.width, b_size=size
        )
        hit, will, tx, ty = h & near, w & near, x_, y_
    impact = cars.impact | will
    out = {
        "crashed": torch.cat([cars.crashed | hit, v.crashed[:, o:] | hit.any(-1, keepdim=True)], 1),
        "impact": torch.cat([impact, v.impact[:, o:]], 1),
        "impact_x": torch.cat([torch.where(will, tx, cars.impact_x), v.impact_x[:, o:]], 1),
        "impact_y": torch.cat([torch.where(will, ty, cars.impact_y), v.impact_y[:, o:]], 1),
    }
    rest = {
        k: torch.cat([getattr(cars, k), getattr(v, k)[:, o:]], 1)
        for k in Vehicles._fields
        if k not in out
    }
    return Vehicles(**rest, **out)


def merge_substep(world: World, action: torch.Tensor, params: MergeParams) -> World:
    """One simulation frame; ``action`` applies where ``steps`` is a multiple of ``frames``.

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
    index = _ego_act(v, world.speed_index, action, first, cols, params)
    v = v._replace(target_speed=cols["target_speed"])
    scene = _Scene(v, params)
    for me in range(1, params.obstacle_row):
        _idm_act(v, scene, me, cols, params)
    o = params.obstacle_row
    moved = step_vehicles(
        v._replace(**cols),
        params,
        closest=lambda x, y, h: L.closest_lane(x, y, h, params.road.lanes),
    )
    # The obstacle never steps: its row keeps every field.
    moved = Vehicles(
        *(torch.cat([new[:, :o], old[:, o:]], 1) for new, old in zip(moved, v, strict=True))
    )
    moved = _collide(moved, params)
    return world._replace(vehicles=moved, speed_index=index, steps=world.steps + 1)


def merge_step(world: World, action: torch.Tensor, params: MergeParams) -> tuple[World, dict]:
    """``env.step(action)`` for B merge worlds.

    Args:
        world: B worlds (see :mod:`.merge_params` for the rows).
        action: ``[B]`` int64 meta-actions.
        params: the constants.

    Returns:
        ``(worlds after the step, observe_merge of them with this action's reward)``.

    Example:
        >>> # see the module's example
    """
    world = world._replace(time=world.time + params.time.step_time)
    for _ in range(params.time.frames):
        world = merge_substep(world, action, params)
    return world, observe_merge(world, params, action)
