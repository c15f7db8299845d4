"""Collisions after each substep: ``Road.step``'s pairwise ``handle_collisions``.

Pairs ``(i, j)``, ``i < j``, are checked in road order when either vehicle checks
collisions (in highway-fast-v0 only the ego does, so only pairs with the ego). A pair
farther apart than ``diagonal + speed_i * dt`` is skipped (only i's speed counts);
the rest go through the separating-axis test of ``utils.are_polygons_intersecting`` on
the two 5 x 2 m rectangles, with i's rectangle swept by the pair's relative
displacement over ``dt``:

- overlapping now: both vehicles are crashed;
- overlapping once swept: a translation ``T`` (the smallest swept overlap, pointing
  from j's centre to i's) is stored as i's pending impact ``T / 2`` and j's ``-T / 2``;
  a later pair (in road order) overwrites an earlier one, and the impact moves and
  crashes the vehicle at its next substep.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("highway-fast-v0")
    >>> v = empty_world(1, 3, torch.float64).vehicles
    >>> v = v._replace(x=torch.tensor([[0.0, 4.0, 50.0]], dtype=torch.float64),
    ...                check_collisions=torch.tensor([[True, False, False]]))
    >>> out = collide(v, params)
    >>> out.crashed.tolist(), out.impact.tolist()
    ([[True, True, False]], [[True, True, False]])
"""

from __future__ import annotations

import math

import torch

from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.selection import scatter, select
from torchrl_grpo.sim.state import Vehicles, take

__all__ = ["collide", "separating_axes"]


def _corners(x, y, heading, length, width):
    """The 4 corners ``[..., 4]`` (x and y) of each rectangle, in highway-env's order."""
    c, s = torch.cos(heading), torch.sin(heading)
    px = torch.tensor(
        [-length / 2, -length / 2, length / 2, length / 2], dtype=x.dtype, device=x.device
    )
    py = torch.tensor(
        [-width / 2, width / 2, width / 2, -width / 2], dtype=x.dtype, device=x.device
    )
    c, s = c.unsqueeze(-1), s.unsqueeze(-1)
    cx = (c * px + (-s) * py) + x.unsqueeze(-1)
    cy = (s * px + c * py) + y.unsqueeze(-1)
    return cx, cy


def _interval_distance(min_a, max_a, min_b, max_b):
    return torch.where(min_a < min_b, min_b - max_a, min_a - max_b)


def separating_axes(
    a: tuple, b: tuple, dt: float, length: float, width: float, b_size: tuple | None = None
):
    """``are_polygons_intersecting`` for batches of rectangle pairs.

    Args:
        a: ``(x, y, heading, speed)`` of the first rectangles.
        b: the same for the second rectangles (broadcast together to a shape S).
        dt: the sweep time of the displacements ``speed (cos, sin)(heading) dt``.
        length: rectangle length.
        width: rectangle width.
        b_size: ``(length, width)`` of the second rectangles if they differ (an
            obstacle's 2 x 2 m square).

    Returns:
        ``(intersecting, will_intersect, tx, ty)``, each of shape S; the translation
        is meaningful only where ``will_intersect``.

    Example:
        >>> one = lambda v: torch.tensor([v], dtype=torch.float64)
        >>> a = (one(0.0), one(0.0), one(0.0), one(0.0))
        >>> b = (one(4.0), one(0.0), one(0.0), one(0.0))
        >>> hit, will, tx, ty = separating_axes(a, b, 0.2, 5.0, 2.0)
        >>> hit.item(), will.item(), tx.item(), ty.item()
        (True, True, -1.0, 0.0)
    """
    parts = torch.broadcast_tensors(*a, *b)
    a, b = parts[:4], parts[4:]
    ax, ay = _corners(a[0], a[1], a[2], length, width)
    bx, by = _corners(b[0], b[1], b[2], *(b_size or (length, width)))
    # Each rectangle's 4 edges, a's then b's: the 8 candidate axes, [..., 8].
    ex = torch.cat([ax, bx], -1)
    ey = torch.cat([ay, by], -1)
    nx = -torch.cat([ay.roll(-1, -1), by.roll(-1, -1)], -1) + ey
    ny = torch.cat([ax.roll(-1, -1), bx.roll(-1, -1)], -1) - ex
    norm = torch.sqrt(nx * nx + ny * ny)
    nx, ny = nx / norm, ny / norm
    proj_a = ax.unsqueeze(-2) * nx.unsqueeze(-1) + ay.unsqueeze(-2) * ny.unsqueeze(-1)
    proj_b = bx.unsqueeze(-2) * nx.unsqueeze(-1) + by.unsqueeze(-2) * ny.unsqueeze(-1)
    min_a, max_a = proj_a.amin(-1), proj_a.amax(-1)
    min_b, max_b = proj_b.amin(-1), proj_b.amax(-1)
    intersecting = ~(_interval_distance(min_a, max_a, min_b, max_b) > 0).any(-1)

    def displacement(car):
        x, y, heading, speed = car
        return (speed * torch.cos(heading)) * dt, (speed * torch.sin(heading)) * dt

    (dax, day), (dbx, dby) = displacement(a), displacement(b)
    vp = nx * (dax - dbx).unsqueeze(-1) + ny * (day - dby).unsqueeze(-1)
    min_a = torch.where(vp < 0, min_a + vp, min_a)
    max_a = torch.where(vp < 0, max_a, max_a + vp)
    distance = _interval_distance(min_a, max_a, min_b, max_b)
    will = ~(distance > 0).any(-1)
    best = distance.abs().argmin(-1, keepdim=True)
    min_distance = distance.abs().gather(-1, best).squeeze(-1)
    bx_, by_ = nx.gather(-1, best).squeeze(-1), ny.gather(-1, best).squeeze(-1)
    # Centre difference: the mean of 4 corners, summed in order as numpy reduces them.
    dx = ((ax[..., 0] + ax[..., 1] + ax[..., 2]) + ax[..., 3]) / 4 - (
        (bx[..., 0] + bx[..., 1] + bx[..., 2]) + bx[..., 3]
    ) / 4
    dy = ((ay[..., 0] + ay[..., 1] + ay[..., 2]) + ay[..., 3]) / 4 - (
        (by[..., 0] + by[..., 1] + by[..., 2]) + by[..., 3]
    ) / 4
    sign = torch.where(dx * bx_ + dy * by_ > 0, 1.0, -1.0).to(dx.dtype)
    return intersecting, will, min_distance * (sign * bx_), min_distance * (sign * by_)


def _reach(speed: torch.Tensor, params: HighwayParams) -> torch.Tensor:
    """The prefilter's radius: the mean diagonal plus the first vehicle's travel over dt."""
    diagonal = math.sqrt(params.vehicle.length**2 + params.vehicle.width**2)
    return (diagonal + diagonal) / 2 + speed * params.time.dt


def _last(flags: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Whether any flag is set along ``dim``, and the index of the last one set."""
    index = torch.arange(flags.shape[dim], device=flags.device)
    index = index.view(-1, *([1] * (flags.ndim - 1 - (dim % flags.ndim))))
    return flags.any(dim), torch.where(flags, index, -1).amax(dim)


def _ego_pairs(v: Vehicles, params: HighwayParams, dense: bool) -> Vehicles:
    """Only the ego checks collisions: its pairs (0, j), in road order."""
    batch, n = v.x.shape
    ego = tuple(t[:, :1] for t in (v.x, v.y, v.heading, v.speed))
    dx, dy = v.x[:, 1:] - ego[0], v.y[:, 1:] - ego[1]
    near = ~(torch.sqrt(dx * dx + dy * dy) > _reach(ego[3], params)) & v.present[:, 1:]
    hit = torch.zeros_like(near)
    will = torch.zeros_like(near)
    tx = torch.zeros_like(dx)
    ty = torch.zeros_like(dx)
    sel = select(near, dense)
    if not sel.empty:
        # Pair (0, j) is column j - 1 of the others' table.
        fields = (v.x, v.y, v.heading, v.speed)
        car_ego = tuple(t[:, 0].index_select(0, sel.rows) for t in fields)
        car_other = tuple(take(t[:, 1:], sel.at) for t in fields)
        length, width = params.vehicle.length, params.vehicle.width
        h, w, x_, y_ = separating_axes(car_ego, car_other, params.time.dt, length, width)
        if sel.valid is not None:
            h, w = h & sel.valid, w & sel.valid
        hit, will = scatter(hit, sel, h), scatter(will, sel, w)
        tx, ty = scatter(tx, sel, x_), scatter(ty, sel, y_)
    any_will, last = _last(will, -1)
    pick = last.clamp(min=0).unsqueeze(-1)
    impact_x = torch.cat([(tx.gather(1, pick) / 2), -tx / 2], dim=1)
    impact_y = torch.cat([(ty.gather(1, pick) / 2), -ty / 2], dim=1)
    pending = torch.cat([any_will.unsqueeze(-1), will], dim=1)
    crashed = v.crashed | torch.cat([hit.any(-1, keepdim=True), hit], dim=1)
    return _with_impacts(v, crashed, pending, impact_x, impact_y)


def _all_pairs(v: Vehicles, params: HighwayParams) -> Vehicles:
    """Every pair (i, j), i < j, where one of them checks: prefiltered, then tested."""
    batch, n = v.x.shape
    dx = v.x.unsqueeze(1) - v.x.unsqueeze(2)  # [b, i, j] = x_j - x_i
    dy = v.y.unsqueeze(1) - v.y.unsqueeze(2)
    checks = v.check_collisions.unsqueeze(2) | v.check_collisions.unsqueeze(1)
    both = v.present.unsqueeze(2) & v.present.unsqueeze(1)
    upper = torch.ones(n, n, dtype=torch.bool, device=v.x.device).triu(1)
    near = ~(torch.sqrt(dx * dx + dy * dy) > _reach(v.speed.unsqueeze(2), params))
    rows, i, j = (near & checks & both & upper).nonzero(as_tuple=True)
    at_i, at_j = rows * n + i, rows * n + j  # flat index_select: faster than t[rows, i]
    car_i = tuple(take(t, at_i) for t in (v.x, v.y, v.heading, v.speed))
    car_j = tuple(take(t, at_j) for t in (v.x, v.y, v.heading, v.speed))
    hit, will, tx, ty = separating_axes(
        car_i, car_j, params.time.dt, params.vehicle.length, params.vehicle.width
    )

    def dense(value: torch.Tensor, fill: float) -> torch.Tensor:
        table = torch.full((batch, n, n), fill, dtype=value.dtype, device=v.x.device)
        return table.index_put_((rows, i, j), value)

    hit, will = dense(hit, False), dense(will, False)
    tx, ty = dense(tx, 0.0), dense(ty, 0.0)
    crashed = v.crashed | hit.any(2) | hit.any(1)
    # A later pair overwrites: pairs (k, j) come after every (i, k), i < k.
    as_first, first = _last(will, 2)
    as_second, second = _last(will, 1)
    pick_first, pick_second = first.clamp(min=0).unsqueeze(2), second.clamp(min=0).unsqueeze(1)
    impact_x = torch.where(
        as_first, tx.gather(2, pick_first).squeeze(2) / 2, -tx.gather(1, pick_second).squeeze(1) / 2
    )
    impact_y = torch.where(
        as_first, ty.gather(2, pick_first).squeeze(2) / 2, -ty.gather(1, pick_second).squeeze(1) / 2
    )
    return _with_impacts(v, crashed, as_first | as_second, impact_x, impact_y)


def _with_impacts(v: Vehicles, crashed, pending, impact_x, impact_y) -> Vehicles:
    # Every impact was applied (and cleared) by the substep's motion: only new ones remain.
    zero = torch.zeros_like(impact_x)
    return v._replace(
        crashed=crashed,
        impact=pending,
        impact_x=torch.where(pending, impact_x, zero),
        impact_y=torch.where(pending, impact_y, zero),
    )


def collide(v: Vehicles, params: HighwayParams, dense: bool = False) -> Vehicles:
    """Crash flags and pending impacts after every vehicle stepped.

    Args:
        v: the vehicle table after the substep's motion.
        params: the constants.
        dense: test every ego pair, masked, instead of the close ones (static shapes;
            highway-v0's all-pairs mode always compacts).

    Returns:
        The table with ``crashed``, ``impact``, ``impact_x``, ``impact_y`` updated.

    Example:
        >>> # see the module's example
    """
    if params.traffic.others_check_collisions:
        return _all_pairs(v, params)
    return _ego_pairs(v, params, dense)
