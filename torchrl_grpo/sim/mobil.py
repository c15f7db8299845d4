"""MOBIL lane changes of the other vehicles, and the abort of a change already under way.

``IDMVehicle.change_lane_policy`` runs in every substep, for every vehicle that is not
crashed, in road order:

- a vehicle whose lane differs from its target lane is changing lanes. It aborts (its
  target becomes its lane) if some other vehicle, not in that target lane but heading
  for it, is ahead of it by less than the IDM desired gap;
- otherwise, once its timer passes ``lane_change_delay``, the timer restarts and each
  side lane (left, then right: right wins if both pass) that is reachable is taken if
  the vehicle moves (``|v| >= 1``) and MOBIL accepts it: the new follower would not
  brake harder than ``lane_change_max_braking_imposed``, and the acceleration gain
  (plus politeness times the followers' gains) reaches ``lane_change_min_acc_gain``.

The abort test reads other vehicles' target lanes, which vehicles EARLIER in road
order may have changed in the same substep. MOBIL's decisions depend only on
positions, so they are computed first; aborts can chain (an earlier abort removes a
vehicle from a later one's test), and are resolved by passes until nothing changes,
as the sequential loop would decide them.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> from torchrl_grpo.sim.neighbours import lane_index
    >>> params = tensor_params("highway-fast-v0")
    >>> v = empty_world(1, 3, torch.float64).vehicles
    >>> v = v._replace(x=torch.tensor([[0.0, 100.0, 120.0]], dtype=torch.float64),
    ...     speed=torch.full((1, 3), 25.0, dtype=torch.float64),
    ...     target_speed=torch.tensor([[25.0, 30.0, 20.0]], dtype=torch.float64),
    ...     delta=torch.full((1, 3), 4.0, dtype=torch.float64),
    ...     timer=torch.tensor([[0.0, 1.5, 0.0]], dtype=torch.float64),
    ...     lane=torch.tensor([[0, 1, 1]]), target_lane=torch.tensor([[0, 1, 1]]),
    ...     y=torch.tensor([[0.0, 4.0, 4.0]], dtype=torch.float64))
    >>> idx = lane_index(v.x, v.y, v.present, params.road)
    >>> target, timer = lane_change_policy(v, drivers_of(v, idx, params), idx, params)
    >>> target.tolist(), timer.tolist()  # vehicle 1, blocked by 2, goes right (lane 2)
    ([[0, 2, 1]], [[0.0, 0.0, 0.0]])
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from torchrl_grpo.sim.idm import Car, desired_gap, free_road, gather_car, interaction
from torchrl_grpo.sim.neighbours import LaneIndex, neighbours
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.road import is_reachable
from torchrl_grpo.sim.selection import scatter, select
from torchrl_grpo.sim.state import Vehicles, take

__all__ = ["Drivers", "drivers_of", "lane_change_policy", "mobil_accepts"]


class Drivers(NamedTuple):
    """What a substep computes once for every vehicle and the lane-change policy reuses.

    Attributes:
        table: every vehicle as a :class:`~torchrl_grpo.sim.idm.Car` of ``[B, N]`` tensors.
        free: ``[B, N]`` each vehicle's free-road acceleration (its own exponent).
        front: ``[B, N]`` each vehicle's front vehicle in its own lane (-1: none).
        rear: ``[B, N]`` its rear vehicle there.
        acc: ``[B, N]`` its IDM acceleration behind ``front``.
    """

    table: Car
    free: torch.Tensor
    front: torch.Tensor
    rear: torch.Tensor
    acc: torch.Tensor


def drivers_of(v: Vehicles, index: LaneIndex, params: HighwayParams) -> Drivers:
    """Every vehicle's :class:`Drivers` terms for this substep.

    Args:
        v: the vehicle table.
        index: the substep's lane index.
        params: the constants.

    Returns:
        The :class:`Drivers`.

    Example:
        >>> # see the module's example
    """
    batch, n = v.x.shape
    table = Car(v.x, v.speed, torch.cos(v.heading), torch.sin(v.heading), v.target_speed)
    free = free_road(table, v.delta, params)
    rows = torch.arange(batch, device=v.x.device).repeat_interleave(n)
    vehicles = torch.arange(n, device=v.x.device).repeat(batch)
    front, rear = neighbours(index, rows, vehicles, v.lane.flatten())
    ahead = Car(*(t.view(batch, n) for t in gather_car(table, rows, front)))
    acc = free - interaction(table, ahead, params)
    return Drivers(table, free, front.view(batch, n), rear.view(batch, n), acc)


def mobil_accepts(
    v: Vehicles,
    drivers: Drivers,
    index: LaneIndex,
    rows: torch.Tensor,
    vehicle: torch.Tensor,
    candidate: torch.Tensor,
    params: HighwayParams,
) -> torch.Tensor:
    """``IDMVehicle.mobil(candidate)`` for a batch of deciding vehicles.

    Args:
        v: the vehicle table.
        drivers: the substep's per-vehicle IDM terms.
        index: the substep's lane index.
        rows: ``[Q]`` the world of each decider.
        vehicle: ``[Q]`` the deciders.
        candidate: ``[Q]`` a valid lane id per decider.
        params: the constants.

    Returns:
        ``[Q]`` bool, whether MOBIL accepts the change.

    Example:
        >>> # see the module's example
    """
    idm = params.idm
    table = drivers.table
    new_front, new_rear = neighbours(index, rows, vehicle, candidate)
    me = gather_car(table, rows, vehicle)._replace(exists=None)
    new_preceding, new_following = (
        gather_car(table, rows, new_front),
        gather_car(table, rows, new_rear),
    )
    # Flat index_select (take) rather than advanced indexing: the same values, faster.
    at = rows * v.x.shape[1] + vehicle
    delta = take(v.delta, at)
    # The new follower is evaluated with the decider's exponent, as highway-env does.
    new_following_free = free_road(new_following, delta, params)
    new_following_pred_a = new_following_free - interaction(new_following, me, params)
    unsafe = new_following_pred_a < -idm.lane_change_max_braking_imposed
    self_pred_a = take(drivers.free, at) - interaction(me, new_preceding, params)
    self_a = take(drivers.acc, at)
    jerk = self_pred_a - self_a
    if idm.politeness != 0:
        # With politeness 0 (highway-env's value) the followers' terms vanish exactly.
        new_following_a = new_following_free - interaction(new_following, new_preceding, params)
        old_preceding = gather_car(table, rows, drivers.front[rows, vehicle])
        old_following = gather_car(table, rows, drivers.rear[rows, vehicle])
        old_following_free = free_road(old_following, delta, params)
        old_following_a = old_following_free - interaction(old_following, me, params)
        old_following_pred_a = old_following_free - interaction(
            old_following, old_preceding, params
        )
        others = new_following_pred_a - new_following_a + old_following_pred_a - old_following_a
        jerk = jerk + idm.politeness * others
    return ~unsafe & ~(jerk < idm.lane_change_min_acc_gain)


def lane_change_policy(
    v: Vehicles, drivers: Drivers, index: LaneIndex, params: HighwayParams, dense: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """The other vehicles' target lanes and timers after their ``change_lane_policy``.

    Only the vehicles with a decision to take are computed (see :mod:`.selection`):
    those whose timer is due (MOBIL) and those changing lanes (the abort test).

    Args:
        v: the vehicle table before the others act (the ego's target already set).
        drivers: the substep's per-vehicle IDM terms.
        index: the substep's lane index.
        params: the constants.
        dense: compute every vehicle with masks (static shapes) instead of compacting.

    Returns:
        ``(target_lane, timer)``: the new ``[B, N]`` targets and timers.

    Example:
        >>> # see the module's example
    """
    lanes = params.road.lanes_count
    acting = v.present & ~v.crashed
    acting[:, 0] = False  # the ego is driven by its meta-actions
    changing = v.lane != v.target_lane
    due = acting & ~changing & (params.idm.lane_change_delay < v.timer)
    timer = torch.where(due, torch.zeros_like(v.timer), v.timer)
    target = v.target_lane
    sel = select(due, dense)
    if not sel.empty:
        lane = take(v.lane, sel.at)
        x, y = take(v.x, sel.at), take(v.y, sel.at)
        moving = ~(take(v.speed, sel.at).abs() < 1)
        decided = lane
        for side in (-1, 1):  # left, then right: right wins when both pass
            candidate = lane + side
            exists = (candidate >= 0) & (candidate < lanes)
            candidate = candidate.clamp(0, lanes - 1)
            ok = exists & is_reachable(x, y, candidate, params.road) & moving
            ok = ok & mobil_accepts(v, drivers, index, sel.rows, sel.vehicle, candidate, params)
            decided = torch.where(ok, candidate, decided)
        target = scatter(target, sel, decided)
    aborting = acting & changing
    if dense:
        target = _aborts_in_order(v, drivers.table, target, aborting, params)
    elif bool(aborting.any()):
        target = _aborts_by_passes(v, drivers.table, target, aborting, params)
    return target, timer


def _blocks(v: Vehicles, table: Car, rows: torch.Tensor, me: torch.Tensor, params: HighwayParams):
    """``[Q, N]``: vehicle j would block the change of vehicle ``me`` of world ``rows``.

    j is present, not ``me``, not in ``me``'s target lane, and ahead of it by less than
    its desired gap; whether j heads for that lane is checked by the callers, against
    the targets as the sequential loop sees them.
    """
    n = v.x.shape[1]
    at = rows * n + me
    mine = Car(*(take(t, at).unsqueeze(1) for t in table[:5]))
    other = Car(*(t.index_select(0, rows) for t in table[:5]))
    ahead = other.x - mine.x
    gap = desired_gap(mine, other, params)
    target = take(v.target_lane, at).unsqueeze(1)
    others = torch.arange(n, device=v.x.device)
    blocks = (others != me.unsqueeze(1)) & v.present.index_select(0, rows)
    blocks = blocks & (v.lane.index_select(0, rows) != target)
    return blocks & (0 < ahead) & (ahead < gap), target


def _aborts_by_passes(
    v: Vehicles, table: Car, decided: torch.Tensor, aborting: torch.Tensor, params: HighwayParams
) -> torch.Tensor:
    """Aborts of the changing vehicles, compacted: passes until nothing changes.

    Vehicle i sees the new targets of the vehicles before it in road order and the old
    ones of those after it; an abort of an earlier vehicle can unblock a later one, so
    passes repeat until the aborts are a fixed point (one pass, nearly always).
    """
    n = v.x.shape[1]
    rows, me = aborting.nonzero(as_tuple=True)
    blocks, target = _blocks(v, table, rows, me, params)
    earlier = torch.arange(n, device=v.x.device) < me.unsqueeze(1)
    old = v.target_lane.index_select(0, rows)
    aborted = torch.zeros_like(aborting)
    for _ in range(n):
        new = torch.where(aborted, v.lane, decided).index_select(0, rows)
        seen = torch.where(earlier, new, old)
        now = torch.zeros_like(aborting)
        now[rows, me] = (blocks & (seen == target)).any(-1)
        if torch.equal(now, aborted):
            break
        aborted = now
    return torch.where(aborted, v.lane, decided)


def _aborts_in_order(
    v: Vehicles, table: Car, decided: torch.Tensor, aborting: torch.Tensor, params: HighwayParams
) -> torch.Tensor:
    """Aborts of the changing vehicles, dense: one vehicle after the other, in road order."""
    batch, n = v.x.shape
    rows = torch.arange(batch, device=v.x.device).repeat_interleave(n)
    me = torch.arange(n, device=v.x.device).repeat(batch)
    blocks, target = _blocks(v, table, rows, me, params)
    blocks = blocks.view(batch, n, n) & aborting.unsqueeze(-1)
    target = target.view(batch, n)
    column = torch.arange(n, device=v.x.device)
    new = decided
    for i in range(1, n):  # the ego (row 0) never aborts
        seen = torch.where(column < i, new, v.target_lane)
        aborted = (blocks[:, i] & (seen == target[:, i : i + 1])).any(-1)
        new = torch.where((column == i) & aborted.unsqueeze(-1), v.lane, new)
    return new
