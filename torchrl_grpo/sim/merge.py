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

import math

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.collision import _all_pairs, separating_axes
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


def _static_follow(params: MergeParams):
    """``follow_road`` where the hand-over at each lane's end is fixed (no routes).

    A follow function takes ``(rows, x, y, target, mask)``: the vehicle table's columns
    ``rows`` (a slice), their positions and target lanes ``[B, K]``, and where
    ``follow_road`` runs; it returns the targets (kept outside ``mask``). The roundabout
    passes one that follows each vehicle's route.
    """

    def follow(rows: slice, x, y, target, mask) -> torch.Tensor:
        del rows
        return torch.where(mask, _follow_road(x, y, target, params), target)

    return follow


def _steer(x, y, speed, heading, target, params: MergeParams) -> torch.Tensor:
    """``steering_control(target)`` on any lane of the graph."""
    geo = params.road.lanes
    s, r = L.local_coordinates(x, y, target, geo)
    future = L.heading_at(s + speed * params.control.tau_pursuit, target, geo)
    return steer_to(r, future, speed, heading, params)


def _pick(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``table[b, index[b, k]]`` for ``[B, N]`` tables and ``[B, K]`` indices (-1 clamped to 0)."""
    return table.gather(1, index.clamp(min=0))


class _Others:
    """The IDM vehicles (rows ``1 .. obstacle_row - 1``) deciding at once, as ``[B, K]`` tensors.

    What they read and no decision of this substep changes: positions, speeds, lanes,
    target speeds; each vehicle's coordinates along its own current lane.
    """

    def __init__(self, v: Vehicles, params: MergeParams) -> None:
        self.v, self.params, self.geo = v, params, params.road.lanes
        n = v.x.shape[1]
        self.ids = torch.arange(1, params.obstacle_row, device=v.x.device)
        self.rows = self.ids.expand(v.x.shape[0], -1)  # [B, K]
        self.cos, self.sin = torch.cos(v.heading), torch.sin(v.heading)
        # The obstacle is found in front, but is no Vehicle as a follower nor in the abort scan.
        self.is_vehicle = torch.arange(n, device=v.x.device) < params.obstacle_row
        self.not_me = self.ids.unsqueeze(1) != torch.arange(n, device=v.x.device)  # [K, N]
        self.lane = v.lane[:, 1 : params.obstacle_row]
        self.s_cur, self.r_cur = self.frames(self.lane)
        self.s_me = self.diagonal(self.s_cur)

    def frames(self, lane: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``[B, K, N]``: every row's (s, r) in lane ``lane[b, k]``."""
        v = self.v
        return L.local_coordinates(v.x.unsqueeze(1), v.y.unsqueeze(1), lane.unsqueeze(2), self.geo)

    def diagonal(self, table: torch.Tensor) -> torch.Tensor:
        """``[B, K]``: entry ``[b, k, row k]`` of a ``[B, K, N]`` table."""
        return table.gather(2, self.rows.unsqueeze(2)).squeeze(2)

    def car(self, rows: torch.Tensor, s: torch.Tensor, exists=None) -> Car:
        """The :class:`~.idm.Car` of ``rows`` (``[B, K]``), placed at ``s`` along a lane."""
        v = self.v
        fields = (v.speed, self.cos, self.sin, v.target_speed)
        return Car(s, *(_pick(t, rows) for t in fields), exists)

    def neighbours(self, lane, frames=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``Road.neighbour_vehicles(vehicle k, lane[b, k])``: front and rear rows (-1: none)."""
        s, r = self.frames(lane) if frames is None else frames
        member = L.on_lane(
            s, r, lane.unsqueeze(2), self.geo, margin=1.0
        ) & self.v.present.unsqueeze(1)
        member = member & self.not_me
        mine = self.diagonal(s).unsqueeze(2)
        inf = torch.full_like(s, float("inf"))
        ahead = torch.where(member & (mine <= s), s, inf)
        n = s.shape[2]
        # Ties: the later row in front (``s_v <= s_front``), the first behind (``s_v > s_rear``).
        front = torch.where(ahead.amin(-1) < float("inf"), (n - 1) - ahead.flip(-1).argmin(-1), -1)
        behind = torch.where(member & (s < mine), s, -inf)
        rear = torch.where(behind.amax(-1) > -float("inf"), behind.argmax(-1), -1)
        return front, rear

    def behind(self, front: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
        """IDM's acceleration of each vehicle behind ``front``, measured along its own lane."""
        me = self.car(self.rows, self.s_me)
        ahead = self.car(
            front, self.s_cur.gather(2, front.clamp(min=0).unsqueeze(2)).squeeze(2), front >= 0
        )
        return free - interaction(me, ahead, self.params)

    def mobil(self, candidate, acc_now, free, target) -> torch.Tensor:
        """``IDMVehicle.mobil(candidate)`` of every vehicle (route-less: the plain test).

        ``target`` (the targets decided so far) is what a route's test reads.
        """
        del target
        unsafe, mine = self.mobil_parts(candidate, free)
        # Politeness is 0 in highway-env; merge_config refuses other values.
        jerk = mine - acc_now
        return ~unsafe & ~(jerk < self.params.idm.lane_change_min_acc_gain)

    def mobil_parts(self, candidate, free) -> tuple[torch.Tensor, torch.Tensor]:
        """``(unsafe for the new follower, my IDM behind the new front)`` of a candidate lane."""
        v, params, idm = self.v, self.params, self.params.idm
        new_front, new_rear = self.neighbours(candidate)
        delta = v.delta[:, 1 : params.obstacle_row]
        # The new follower brakes for me, along ITS current lane, with MY exponent.
        rear_lane = _pick(v.lane, new_rear)
        s_rear, _ = L.local_coordinates(
            _pick(v.x, new_rear), _pick(v.y, new_rear), rear_lane, self.geo
        )
        s_me, _ = L.local_coordinates(
            v.x[:, 1 : params.obstacle_row], v.y[:, 1 : params.obstacle_row], rear_lane, self.geo
        )
        exists = (new_rear >= 0) & self.is_vehicle[new_rear.clamp(min=0)]
        follower = self.car(new_rear, s_rear, exists)
        pred = free_road(follower, delta, params) - interaction(
            follower, self.car(self.rows, s_me), params
        )
        unsafe = pred < -idm.lane_change_max_braking_imposed
        return unsafe, self.behind(new_front, free)


def _aborts(o: _Others, old, follow, decided, changing, acting, ego_target) -> torch.Tensor:
    """The abort scans, vehicle after vehicle in road order, and the final targets.

    Vehicle k aborts (target = lane) if another vehicle, not in k's target lane but
    heading for it, is ahead along k's lane by less than k's desired gap; it sees the
    final targets of the vehicles before it (the ego's included) and the targets the
    ones after it had before this substep.
    """
    v, params = o.v, o.params
    road_of = _const(params.road.road, v.x)
    me = Car(*(t.unsqueeze(2) for t in o.car(o.rows, o.s_me)[:5]))
    gap = desired_gap(
        me,
        Car(
            o.s_cur,
            v.speed.unsqueeze(1),
            o.cos.unsqueeze(1),
            o.sin.unsqueeze(1),
            v.target_speed.unsqueeze(1),
        ),
        params,
    )
    d = o.s_cur - o.s_me.unsqueeze(2)
    blocks = (
        o.is_vehicle & o.not_me & (v.lane.unsqueeze(1) != follow.unsqueeze(2)) & (0 < d) & (d < gap)
    )
    scan = changing & (road_of[o.lane] == road_of[follow]) & acting
    final = torch.where(acting, decided, old)
    if not bool((scan & blocks.any(-1)).any()):
        return final
    seen = torch.cat([ego_target.unsqueeze(1), old], 1)  # the vehicles' targets before this substep
    for k in range(final.shape[1]):
        heading_there = seen == follow[:, k : k + 1]
        aborted = scan[:, k] & (blocks[:, k, : seen.shape[1]] & heading_there).any(-1)
        final[:, k] = torch.where(aborted, o.lane[:, k], final[:, k])
        seen[:, k + 1] = final[:, k]
    return final


def _others_act(
    v: Vehicles, cols: dict, params: MergeParams, follow_road=None, others=_Others
) -> None:
    """Every IDM vehicle's ``act()``, writing targets, timers and commands into ``cols``.

    ``follow_road`` (see :func:`_static_follow`) and ``others`` (the class that decides)
    are the merge's by default; the roundabout passes its routed ones.
    """
    geo, road, idm = params.road.lanes, params.road, params.idm
    follow_road = follow_road or _static_follow(params)
    o = others(v, params)
    k = slice(1, params.obstacle_row)
    x, y, speed, heading = v.x[:, k], v.y[:, k], v.speed[:, k], v.heading[:, k]
    acting = ~v.crashed[:, k]
    old = cols["target_lane"][:, k].clone()
    # Crashed vehicles skip act(): their targets (and routes) stay as they are.
    follow = follow_road(k, x, y, old, acting)
    changing = o.lane != follow
    free = free_road(o.car(o.rows, o.s_me), v.delta[:, k], params)
    acc = o.behind(o.neighbours(o.lane, (o.s_cur, o.r_cur))[0], free)
    # MOBIL, every lane_change_delay seconds, for the vehicles not changing lanes.
    due = acting & ~changing & (idm.lane_change_delay < cols["timer"][:, k])
    timer = torch.where(due, torch.zeros_like(x), cols["timer"][:, k])
    decided = follow
    if bool(due.any()):
        moving = ~(speed.abs() < 1)
        for side in (road.side_left, road.side_right):  # left, then right: right wins
            candidate = _const(side, x)[o.lane]
            exists = candidate >= 0
            candidate = candidate.clamp(min=0)
            s_c, r_c = L.local_coordinates(x, y, candidate, geo)
            ok = due & exists & moving & L.is_reachable(s_c, r_c, candidate, geo)
            if bool(ok.any()):
                ok = ok & o.mobil(candidate, acc, free, decided)
                decided = torch.where(ok, candidate, decided)
    target = _aborts(o, old, follow, decided, changing, acting, cols["target_lane"][:, 0])
    steer = _steer(x, y, speed, heading, target, params)
    off = o.lane != target
    if bool(off.any()):  # while changing lanes, IDM also brakes for the target lane's front
        acc = torch.where(off, torch.minimum(acc, o.behind(o.neighbours(target)[0], free)), acc)
    acc = torch.clamp(acc, -idm.acc_max, idm.acc_max)
    for name, value in (
        ("target_lane", target),
        ("timer", timer),
        ("steering", steer),
        ("acceleration", acc),
    ):
        cols[name][:, k] = torch.where(acting, value, cols[name][:, k])


def _ego_act(v: Vehicles, index, action, first, cols: dict, params: MergeParams, follow_road=None):
    """The MDP ego's ``act(action)`` (first frame) and ``act()``: target lane, speed, commands."""
    geo, speeds = params.road.lanes, params.control.target_speeds
    x, y, speed = v.x[:, 0], v.y[:, 0], v.speed[:, 0]
    follow_road = follow_road or _static_follow(params)

    def follow(target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        one = (t.unsqueeze(1) for t in (x, y, target, mask))
        return follow_road(slice(0, 1), *one).squeeze(1)

    target = follow(v.target_lane[:, 0], torch.ones_like(first))
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
    target = follow(target, first)
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
    # The prefilter: (the car's diagonal + the obstacle's) / 2 + the car's travel over dt.
    car = math.sqrt(params.vehicle.length**2 + params.vehicle.width**2)
    obstacle = math.sqrt(traffic.obstacle_length**2 + traffic.obstacle_width**2)
    reach = (car + obstacle) / 2 + cars.speed * params.time.dt
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
    _others_act(v, cols, params)
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
