"""Lane geometry of a road graph: ``StraightLane``, ``SineLane`` and ``CircularLane`` as tensors.

A road is a flat list of lanes (highway-env's ``RoadNetwork`` graph in its iteration
order, which is also ``np.argmin``'s tie order in ``get_closest_lane_index``). Each
lane's constants are plain Python floats in a :class:`LaneGeometry`, copied from
highway-env's own lane objects (the env package reads them), and every function takes
a tensor of lane ids, gathers the constants and follows ``road/lane.py`` operation by
operation:

- a ``StraightLane`` is a ``SineLane`` of amplitude 0: ``r0 - 0 * sin(.)`` is ``r0`` and
  ``heading + arctan(0)`` is ``heading`` bit for bit, so one formula serves both;
- a ``CircularLane`` (``kind`` 1) reads its angle with ``atan2``, wrapped around the
  start phase, and its radius as ``sqrt(fma(dy, dy, dx * dx))``, as numpy's BLAS
  computes ``np.linalg.norm`` of a 2-vector on the machines where parity was measured.

Example:
    >>> import torch
    >>> geo = LaneGeometry.of([straight((0.0, 0.0), (100.0, 0.0))])
    >>> lane = torch.zeros(2, dtype=torch.int64)
    >>> x, y = torch.tensor([10.0, 50.0], dtype=torch.float64), torch.tensor([1.0, -3.0])
    >>> s, r = local_coordinates(x, y.double(), lane, geo)
    >>> s.tolist(), r.tolist()
    ([10.0, 50.0], [1.0, -3.0])
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields

import torch

__all__ = [
    "LaneGeometry",
    "after_end",
    "closest_lane",
    "distance_with_heading",
    "heading_at",
    "is_reachable",
    "lane_distance",
    "local_coordinates",
    "on_lane",
    "position",
    "straight",
]

#: ``AbstractLane.VEHICLE_LENGTH``: the longitudinal margin of ``on_lane`` and reachability.
VEHICLE_LENGTH = 5.0


@dataclass(frozen=True)
class LaneGeometry:
    """Every lane's constants, one tuple entry per lane in the road's flat order.

    Attributes:
        kind: 0 for straight and sine lanes, 1 for circular lanes.
        start_x: straight/sine start point (m).
        start_y: see ``start_x``.
        dir_x: unit direction of the chord.
        dir_y: see ``dir_x``.
        lat_x: unit lateral direction ``(-dir_y, dir_x)``.
        lat_y: see ``lat_x``.
        heading: the chord's heading (rad).
        length: the lane's length (m).
        width: the lane's width (m).
        amplitude: sine amplitude (0 for straight lanes).
        pulsation: sine pulsation (rad/m).
        phase: sine phase (rad).
        center_x: circle centre (circular lanes).
        center_y: see ``center_x``.
        radius: circle radius (m).
        start_phase: the circle's start angle (rad).
        turn: ``1`` clockwise, ``-1`` counter-clockwise (highway-env's ``direction``).
        forbidden: the lane cannot be entered by a lane change.

    Example:
        >>> LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0))]).count
        1
    """

    kind: tuple[int, ...]
    start_x: tuple[float, ...]
    start_y: tuple[float, ...]
    dir_x: tuple[float, ...]
    dir_y: tuple[float, ...]
    lat_x: tuple[float, ...]
    lat_y: tuple[float, ...]
    heading: tuple[float, ...]
    length: tuple[float, ...]
    width: tuple[float, ...]
    amplitude: tuple[float, ...]
    pulsation: tuple[float, ...]
    phase: tuple[float, ...]
    center_x: tuple[float, ...]
    center_y: tuple[float, ...]
    radius: tuple[float, ...]
    start_phase: tuple[float, ...]
    turn: tuple[float, ...]
    forbidden: tuple[bool, ...]

    @staticmethod
    def of(lanes: list[dict]) -> LaneGeometry:
        """Stack per-lane dicts (as :func:`straight` makes them) into a geometry.

        Example:
            >>> LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0))]).length
            (10.0,)
        """
        return LaneGeometry(
            **{f.name: tuple(lane[f.name] for lane in lanes) for f in fields(LaneGeometry)}
        )

    @property
    def count(self) -> int:
        """The number of lanes."""
        return len(self.kind)


def straight(start: tuple[float, float], end: tuple[float, float], width: float = 4.0) -> dict:
    """One straight lane's constants, computed as ``StraightLane.__init__`` does (float64).

    Example:
        >>> straight((0.0, 0.0), (0.0, 5.0))["heading"] == math.pi / 2
        True
    """
    dx, dy = end[0] - start[0], end[1] - start[1]
    length = math.hypot(dx, dy)
    ux, uy = dx / length, dy / length
    return {
        "kind": 0, "start_x": start[0], "start_y": start[1], "dir_x": ux, "dir_y": uy,
        "lat_x": -uy, "lat_y": ux, "heading": math.atan2(dy, dx), "length": length,
        "width": width, "amplitude": 0.0, "pulsation": 0.0, "phase": 0.0, "center_x": 0.0,
        "center_y": 0.0, "radius": 1.0, "start_phase": 0.0, "turn": 1.0, "forbidden": False,
    }  # fmt: skip


@functools.lru_cache(maxsize=256)
def _table(
    geo: LaneGeometry, names: tuple[str, ...], dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """``[L, len(names)]``: the named constants per lane (booleans and kinds as floats)."""
    columns = [getattr(geo, name) for name in names]
    return torch.tensor(list(zip(*columns, strict=True)), dtype=dtype, device=device)


def _gather(
    geo: LaneGeometry, lane: torch.Tensor, like: torch.Tensor, *names: str
) -> dict[str, torch.Tensor]:
    """The named constants of each lane, shaped like ``lane`` (they broadcast from there).

    One ``index_select`` of whole rows of the columns asked for: far cheaper on a CPU than
    an advanced index per field, and done at ``lane``'s own shape, before broadcasting.
    """
    table = _table(geo, names, like.dtype, like.device)
    rows = table.index_select(0, lane.reshape(-1)).view(*lane.shape, len(names))
    return dict(zip(names, rows.unbind(-1), strict=True))


_STRAIGHT = ("start_x", "start_y", "dir_x", "dir_y", "lat_x", "lat_y")
_SINE = ("amplitude", "pulsation", "phase")
_ROUND = ("kind", "center_x", "center_y", "radius", "start_phase", "turn")


def _circular(geo: LaneGeometry) -> bool:
    return any(k == 1 for k in geo.kind)


def wrap_to_pi(x: torch.Tensor) -> torch.Tensor:
    """``utils.wrap_to_pi``: ``((x + pi) mod 2 pi) - pi`` with a floor modulo.

    Example:
        >>> round(float(wrap_to_pi(torch.tensor(4.0, dtype=torch.float64))), 6)
        -2.283185
    """
    return torch.remainder(x + math.pi, 2 * math.pi) - math.pi


def local_coordinates(
    x: torch.Tensor, y: torch.Tensor, lane: torch.Tensor, geo: LaneGeometry
) -> tuple[torch.Tensor, torch.Tensor]:
    """``lane.local_coordinates(position)``: (longitudinal, lateral), broadcast over the inputs.

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 4.0), (10.0, 4.0))])
        >>> s, r = local_coordinates(torch.tensor(3.0), torch.tensor(5.0), torch.tensor(0), geo)
        >>> s.item(), r.item()
        (3.0, 1.0)
    """
    c = _gather(geo, lane, x, *_STRAIGHT, *_SINE, *(_ROUND if _circular(geo) else ()))
    dx, dy = x - c["start_x"], y - c["start_y"]
    # np.dot of 2-vectors: fma(d1, u1, d0 * u0); exact for the axis-aligned lanes here.
    s = torch.addcmul(dx * c["dir_x"], dy, c["dir_y"])
    r = torch.addcmul(dx * c["lat_x"], dy, c["lat_y"])
    r = r - c["amplitude"] * torch.sin(c["pulsation"] * s + c["phase"])
    if _circular(geo):
        cx, cy = x - c["center_x"], y - c["center_y"]
        phi = torch.atan2(cy, cx)
        phi = c["start_phase"] + wrap_to_pi(phi - c["start_phase"])
        rho = torch.sqrt(torch.addcmul(cx * cx, cy, cy))
        s_c = c["turn"] * (phi - c["start_phase"]) * c["radius"]
        r_c = c["turn"] * (c["radius"] - rho)
        round_ = c["kind"] == 1
        s, r = torch.where(round_, s_c, s), torch.where(round_, r_c, r)
    return s, r


def position(
    s: torch.Tensor, r: torch.Tensor, lane: torch.Tensor, geo: LaneGeometry
) -> tuple[torch.Tensor, torch.Tensor]:
    """``lane.position(s, r)``: world (x, y).

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 4.0), (10.0, 4.0))])
        >>> x, y = position(torch.tensor(3.0), torch.tensor(1.0), torch.tensor(0), geo)
        >>> x.item(), y.item()
        (3.0, 5.0)
    """
    c = _gather(geo, lane, s, *_STRAIGHT, *_SINE, *(_ROUND if _circular(geo) else ()))
    r_sine = r + c["amplitude"] * torch.sin(c["pulsation"] * s + c["phase"])
    x = (c["start_x"] + s * c["dir_x"]) + r_sine * c["lat_x"]
    y = (c["start_y"] + s * c["dir_y"]) + r_sine * c["lat_y"]
    if _circular(geo):
        phi = c["turn"] * s / c["radius"] + c["start_phase"]
        rho = c["radius"] - r * c["turn"]
        round_ = c["kind"] == 1
        x = torch.where(round_, c["center_x"] + rho * torch.cos(phi), x)
        y = torch.where(round_, c["center_y"] + rho * torch.sin(phi), y)
    return x, y


def heading_at(s: torch.Tensor, lane: torch.Tensor, geo: LaneGeometry) -> torch.Tensor:
    """``lane.heading_at(s)`` (never wrapped, as highway-env leaves it).

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 0.0), (0.0, 5.0))])
        >>> float(heading_at(torch.tensor(1.0, dtype=torch.float64), torch.tensor(0), geo))
        1.5707963267948966
    """
    c = _gather(geo, lane, s, "heading", *_SINE, *(_ROUND if _circular(geo) else ()))
    h = c["heading"] + torch.atan(
        (c["amplitude"] * c["pulsation"]) * torch.cos(c["pulsation"] * s + c["phase"])
    )
    if _circular(geo):
        phi = c["turn"] * s / c["radius"] + c["start_phase"]
        h = torch.where(c["kind"] == 1, phi + math.pi / 2 * c["turn"], h)
    return h


def on_lane(
    s: torch.Tensor, r: torch.Tensor, lane: torch.Tensor, geo: LaneGeometry, margin: float = 0.0
) -> torch.Tensor:
    """``lane.on_lane(position, s, r, margin)``.

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0))])
        >>> on_lane(torch.tensor([1.0, -5.0, 15.0]), torch.tensor([2.0, 0.0, 0.0]),
        ...         torch.tensor(0), geo).tolist()
        [True, True, False]
    """
    c = _gather(geo, lane, s, "width", "length")
    return (
        (r.abs() <= c["width"] / 2 + margin)
        & (-VEHICLE_LENGTH <= s)
        & (s < c["length"] + VEHICLE_LENGTH)
    )


def is_reachable(
    s: torch.Tensor, r: torch.Tensor, lane: torch.Tensor, geo: LaneGeometry
) -> torch.Tensor:
    """``lane.is_reachable_from(position)``, from the position's (s, r) in that lane.

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0))])
        >>> is_reachable(torch.tensor([1.0, -1.0]), torch.tensor([8.0, 0.0]),
        ...              torch.tensor(0), geo).tolist()
        [True, False]
    """
    c = _gather(geo, lane, s, "width", "length", "forbidden")
    close = (r.abs() <= 2 * c["width"]) & (0 <= s) & (s < c["length"] + VEHICLE_LENGTH)
    return close & (c["forbidden"] == 0)


def after_end(s: torch.Tensor, lane: torch.Tensor, geo: LaneGeometry) -> torch.Tensor:
    """``lane.after_end(position)``: past the last half vehicle length.

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0))])
        >>> after_end(torch.tensor([7.5, 7.6]), torch.tensor(0), geo).tolist()
        [False, True]
    """
    return s > _gather(geo, lane, s, "length")["length"] - VEHICLE_LENGTH / 2


def lane_distance(
    x: torch.Tensor, y: torch.Tensor, lane: torch.Tensor, geo: LaneGeometry
) -> torch.Tensor:
    """``lane.distance(position)``: ``|r| + max(s - L, 0) + max(-s, 0)``.

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0))])
        >>> lane_distance(torch.tensor(12.0), torch.tensor(-1.0), torch.tensor(0), geo).item()
        3.0
    """
    s, r = local_coordinates(x, y, lane, geo)
    length = _gather(geo, lane, s, "length")["length"]
    return (r.abs() + torch.clamp(s - length, min=0)) + torch.clamp(0 - s, min=0)


def distance_with_heading(
    x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor, geo: LaneGeometry
) -> torch.Tensor:
    """``lane.distance_with_heading(position, heading)`` for every lane: ``[..., L]``.

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0))])
        >>> distance_with_heading(torch.tensor([12.0]), torch.tensor([1.0]),
        ...                       torch.tensor([0.5]), geo).tolist()
        [[3.5]]
    """
    xs, ys, hs = x.unsqueeze(-1), y.unsqueeze(-1), heading.unsqueeze(-1)
    plain, curved = _split(geo)
    parts = []
    for group, trig in ((plain, False), (curved, True)):
        if not group:
            continue
        lanes = torch.tensor(group, device=x.device)
        if trig:
            s, r = local_coordinates(xs, ys, lanes, geo)
            lane_heading = heading_at(s, lanes, geo)
        else:
            # Straight lanes: a sine of amplitude 0 subtracts and adds exact zeros, so the
            # trigonometry is skipped with the same bits.
            c = _gather(geo, lanes, x, *_STRAIGHT, "heading")
            dx, dy = xs - c["start_x"], ys - c["start_y"]
            s = torch.addcmul(dx * c["dir_x"], dy, c["dir_y"])
            r = torch.addcmul(dx * c["lat_x"], dy, c["lat_y"])
            lane_heading = c["heading"]
        length = _gather(geo, lanes, x, "length")["length"]
        angle = wrap_to_pi(hs - lane_heading).abs()
        parts.append(
            ((r.abs() + torch.clamp(s - length, min=0)) + torch.clamp(0 - s, min=0)) + 1.0 * angle
        )
    out = torch.cat(parts, -1)
    order = _order(geo)
    return out if order is None else out.index_select(-1, torch.tensor(order, device=x.device))


@functools.lru_cache(maxsize=64)
def _split(geo: LaneGeometry) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The straight lanes (no trigonometry) and the others, in flat order each."""
    straight_ = tuple(k for k in range(geo.count) if geo.kind[k] == 0 and geo.amplitude[k] == 0)
    return straight_, tuple(k for k in range(geo.count) if k not in straight_)


@functools.lru_cache(maxsize=64)
def _order(geo: LaneGeometry) -> tuple[int, ...] | None:
    """Where each flat lane sits in ``plain + curved`` (``None``: already in order)."""
    plain, curved = _split(geo)
    joined = plain + curved
    if joined == tuple(range(geo.count)):
        return None
    return tuple(joined.index(k) for k in range(geo.count))


def closest_lane(
    x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor, geo: LaneGeometry
) -> torch.Tensor:
    """``network.get_closest_lane_index(position, heading)`` as a flat lane id (first minimum).

    Example:
        >>> geo = LaneGeometry.of([straight((0.0, 0.0), (10.0, 0.0)),
        ...                        straight((0.0, 4.0), (10.0, 4.0))])
        >>> closest_lane(torch.tensor([5.0, 5.0]), torch.tensor([1.0, 3.0]),
        ...              torch.zeros(2), geo).tolist()
        [0, 1]
    """
    return distance_with_heading(x, y, heading, geo).argmin(-1)
