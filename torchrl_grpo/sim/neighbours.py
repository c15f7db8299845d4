"""The front and rear vehicle of any vehicle in any lane, from one sort per substep.

highway-env's ``Road.neighbour_vehicles(vehicle, lane)`` scans every vehicle: those
within ``lane_width / 2 + 1`` of the lane's centre (a vehicle between two lanes is in
both) and along the lane are members; the front vehicle is the member with the
smallest ``x >= vehicle.x`` (ties: the LAST in road order) and the rear one the member
with the largest ``x < vehicle.x`` (ties: the FIRST in road order); the vehicle itself
is skipped. Recomputing that for every (vehicle, lane) query costs ``B x N x N`` per
lane; here the vehicles are sorted once by (x ascending, road index descending), each
lane's members are marked along that order, and a count of the members before each
position gives, for every sorted position, the next member at or after it and the
last member before it. A query is then two gathers. IDM, MOBIL and the
lane-change abort all read the same :class:`LaneIndex`.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> road = tensor_params("highway-fast-v0").road
    >>> x = torch.tensor([[0.0, 30.0, -2.0, 10.0]])
    >>> y = torch.tensor([[0.0, 0.0, 0.0, 4.0]])
    >>> index = lane_index(x, y, torch.ones(1, 4, dtype=torch.bool), road)
    >>> zero = torch.zeros(2, dtype=torch.int64)
    >>> front, rear = neighbours(index, zero, zero, torch.tensor([0, 1]))
    >>> front.tolist(), rear.tolist()  # vehicle 0 in lanes 0 and 1
    ([1, 3], [2, -1])
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from torchrl_grpo.sim.params import RoadParams
from torchrl_grpo.sim.state import take

__all__ = ["LaneIndex", "lane_index", "neighbours"]


class LaneIndex(NamedTuple):
    """One substep's sorted view of the road.

    Attributes:
        order: ``[B, N]`` the vehicle at each sorted position.
        rank: ``[B, N]`` the sorted position of each vehicle.
        start: ``[B, N]`` the first sorted position whose x is not below the vehicle's.
        next_member: ``[B, L, N + 1]`` the first position at or after p that is a member
            of lane l (N: none).
        prev_member: ``[B, L, N + 1]`` the last position before p that is a member of
            lane l (-1: none).
    """

    order: torch.Tensor
    rank: torch.Tensor
    start: torch.Tensor
    next_member: torch.Tensor
    prev_member: torch.Tensor


def lane_index(
    x: torch.Tensor, y: torch.Tensor, present: torch.Tensor, road: RoadParams
) -> LaneIndex:
    """Sort the vehicles and mark each lane's members.

    Args:
        x: ``[B, N]`` positions along the road.
        y: ``[B, N]`` lateral positions.
        present: ``[B, N]`` rows that hold a vehicle.
        road: the lanes.

    Returns:
        The :class:`LaneIndex` of these positions.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("highway-fast-v0").road
        >>> idx = lane_index(torch.tensor([[5.0, 1.0, 5.0]]), torch.zeros(1, 3),
        ...                  torch.ones(1, 3, dtype=torch.bool), road)
        >>> idx.order.tolist(), idx.start.tolist()  # equal x: higher index first
        ([[1, 2, 0]], [[1, 0, 1]])
    """
    batch, n = x.shape
    key = torch.where(present, x, torch.full_like(x, float("inf")))
    # Sorting the reversed row stably puts equal x in descending road order.
    reversed_order = torch.argsort(key.flip(-1), dim=-1, stable=True)
    order = (n - 1) - reversed_order
    positions = torch.arange(n, device=x.device).expand(batch, n)
    rank = torch.empty_like(order).scatter_(1, order, positions)
    sorted_x = key.gather(1, order)
    start = torch.searchsorted(sorted_x, key.contiguous(), side="left")

    lanes = torch.arange(road.lanes_count, device=x.device)
    lat = y.unsqueeze(1) - (lanes * road.lane_width).to(y.dtype).view(1, -1, 1)
    along = (x >= -road.margin_length) & (x < road.lane_length + road.margin_length)
    member = (lat.abs() <= road.lane_width / 2 + 1) & (along & present).unsqueeze(1)
    member = member.gather(2, order.unsqueeze(1).expand_as(member))

    # The k-th member's position, from a count of members before each position (a
    # cumsum, much cheaper than cummin/cummax scans): next_member[p] is the member
    # numbered "members before p", prev_member[p] the one numbered one less.
    count = member.to(torch.int64).cumsum(-1)
    before = count - member.to(torch.int64)
    pos = positions.unsqueeze(1).expand_as(member)
    slot = torch.where(member, before, torch.full_like(before, n))  # non-members: a dump slot
    kth = torch.full((batch, road.lanes_count, n + 1), n, dtype=torch.int64, device=x.device)
    kth.scatter_(2, slot, pos)
    total = count[..., -1:]
    before = torch.cat([before, total], dim=-1)  # position n: after every vehicle
    next_member = kth.gather(2, before)  # kth[total] is n: none
    prev_member = torch.where(before > 0, kth.gather(2, (before - 1).clamp(min=0)), -1)
    return LaneIndex(order, rank, start, next_member, prev_member)


def neighbours(
    index: LaneIndex, rows: torch.Tensor, vehicle: torch.Tensor, lane: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The front and rear vehicle of each query, as ``Road.neighbour_vehicles`` finds them.

    Args:
        index: the substep's :class:`LaneIndex`.
        rows: ``[Q]`` the world of each query.
        vehicle: ``[Q]`` the querying vehicle.
        lane: ``[Q]`` the lane searched (a valid lane id).

    Returns:
        ``(front, rear)``: ``[Q]`` vehicle indices, -1 where there is none.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("highway-fast-v0").road
        >>> idx = lane_index(torch.tensor([[5.0, 1.0, 5.0]]), torch.zeros(1, 3),
        ...                  torch.ones(1, 3, dtype=torch.bool), road)
        >>> neighbours(idx, torch.zeros(3, dtype=torch.int64), torch.tensor([0, 2, 1]),
        ...            torch.zeros(3, dtype=torch.int64))
        (tensor([2, 0, 2]), tensor([ 1,  1, -1]))
    """
    batch, lanes, width = index.next_member.shape
    n = width - 1
    at = rows * n + vehicle
    start = take(index.start, at)
    rank = take(index.rank, at)
    row = (rows * lanes + lane) * width
    first = take(index.next_member, row + start)
    # The vehicle itself is skipped: the next member after it is then the front one.
    first = torch.where(first == rank, take(index.next_member, row + rank + 1), first)
    front = torch.where(first < n, take(index.order, rows * n + first.clamp(max=n - 1)), -1)
    last = take(index.prev_member, row + start)
    rear = torch.where(last >= 0, take(index.order, rows * n + last.clamp(min=0)), -1)
    return front, rear
