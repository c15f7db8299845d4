"""The Kinematics observation, as ``KinematicObservation.observe`` computes it (``order="sorted"``).

Row 0 is the ego in world coordinates; the next rows are the vehicles closer than
``perception_distance`` (and, without ``see_behind``, less than two lengths behind
the ego), sorted by ``|x - x_ego|`` (ties in road order), relative to the ego unless
``absolute``. x, y, vx and vy are mapped from ``features_range`` to [-1, 1] (the ego's
row too) and clipped; missing rows are zeros. Velocities are ``speed (cos, sin)(heading)``.
``cos_d, sin_d`` point to the end of a vehicle's route (:func:`route_intentions`): the
ego's always, the others' only with ``observe_intentions``; zeros without routes.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("highway-fast-v0")
    >>> v = empty_world(1, 3, torch.float64).vehicles
    >>> v = v._replace(x=torch.tensor([[100.0, 200.0, 500.0]], dtype=torch.float64),
    ...                speed=torch.full((1, 3), 20.0, dtype=torch.float64))
    >>> observe(v, params)[0, :3].tolist()  # vehicle 2 is out of sight (400 m ahead)
    [[1.0, 0.5, 0.0, 0.25, 0.0], [1.0, 0.5, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0]]
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.routes import destination_direction
from torchrl_grpo.sim.state import Vehicles

__all__ = ["FEATURES", "observe", "route_intentions", "shown_vehicles"]

#: The Kinematics features this simulator computes.
FEATURES = ("presence", "x", "y", "vx", "vy", "heading", "cos_h", "sin_h", "cos_d", "sin_d")

_INTENTIONS = ("cos_d", "sin_d")


def route_intentions(world, params) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``(cos_d, sin_d)`` ``[B, N]`` of a routed world's vehicles, if the table shows them.

    ``None`` where the features leave them out or the world has no routes (the table
    then shows zeros, as highway-env does for vehicles without a route).

    Example:
        >>> import torch
        >>> from torchrl_grpo.envs import tensor_params
        >>> from torchrl_grpo.sim.state import empty_world
        >>> params = tensor_params("roundabout-v0")
        >>> world = empty_world(1, 2, torch.float64, route_length=params.route_length)
        >>> route_intentions(world, params) is None  # the default features leave them out
        True
    """
    if world.route is None or not set(_INTENTIONS) & set(params.observation.features):
        return None
    v = world.vehicles
    return destination_direction(v.x, v.y, world.route, world.route_head, params.road)


def _features(
    v: Vehicles, intentions: tuple[torch.Tensor, torch.Tensor] | None
) -> dict[str, torch.Tensor]:
    cos_h, sin_h = torch.cos(v.heading), torch.sin(v.heading)
    cos_d, sin_d = intentions if intentions is not None else (v.x.new_zeros(()),) * 2
    return {
        "presence": torch.ones_like(v.x),
        "x": v.x,
        "y": v.y,
        "vx": v.speed * cos_h,
        "vy": v.speed * sin_h,
        "heading": v.heading,
        "cos_h": cos_h,
        "sin_h": sin_h,
        "cos_d": cos_d.expand_as(v.x),
        "sin_d": sin_d.expand_as(v.x),
    }


def observe(v: Vehicles, params: HighwayParams) -> torch.Tensor:
    """The ``[B, vehicles_count, len(features)]`` table, in the vehicle table's dtype.

    Args:
        v: the vehicle table.
        params: the constants (``params.observation`` describes the table).

    Returns:
        The observation; highway-env casts it to float32, the env does so in float32
        mode.

    Example:
        >>> # see the module's example
    """
    order, shown = shown_vehicles(v, params)
    return kinematics_table(v, params, order, shown)


def shown_vehicles(v: Vehicles, params: HighwayParams) -> tuple[torch.Tensor, torch.Tensor]:
    """Which vehicles the rows ``1..`` of the table show (the module's docstring).

    Args:
        v: the vehicle table.
        params: the constants (``params.observation`` describes the table).

    Returns:
        The shown vehicles' indices in the vehicle table, ``[B, <= vehicles_count - 1]``,
        and whether each of those rows holds one.

    Example:
        >>> import torch
        >>> from torchrl_grpo.envs import tensor_params
        >>> from torchrl_grpo.sim.state import empty_world
        >>> v = empty_world(1, 3, torch.float64).vehicles
        >>> v = v._replace(x=torch.tensor([[100.0, 500.0, 130.0]], dtype=torch.float64))
        >>> order, shown = shown_vehicles(v, tensor_params("highway-fast-v0"))
        >>> order.tolist(), shown.tolist()  # vehicle 1 is out of sight (400 m ahead)
        ([[2, 0, 1]], [[True, False, False]])
    """
    obs = params.observation
    dx = v.x - v.x[:, :1]
    dy = v.y - v.y[:, :1]
    visible = v.present & (torch.sqrt(dx * dx + dy * dy) < obs.perception_distance)
    visible[:, 0] = False
    if not obs.see_behind:
        visible = visible & (-2 * params.vehicle.length < dx)
    key = torch.where(visible, dx.abs(), torch.full_like(dx, float("inf")))
    order = torch.argsort(key, dim=-1, stable=True)[:, : obs.vehicles_count - 1]
    return order, visible.gather(1, order)


def kinematics_table(
    v: Vehicles,
    params,
    order: torch.Tensor,
    shown: torch.Tensor,
    intentions: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """The Kinematics table ``[B, vehicles_count, F]``: the ego, then the rows ``order`` picks.

    Shared by every scenario's observation, which differ only in which vehicles are
    visible and how they are sorted: ``order`` ``[B, <= vehicles_count - 1]`` indexes the
    shown vehicles, ``shown`` says which of those rows hold one (the others are zeros).
    ``intentions`` are :func:`route_intentions` (``None``: zeros).
    """
    obs = params.observation
    feats = _features(v, intentions)
    ego = {k: t[:, :1] for k, t in feats.items()}
    columns = []
    for name in obs.features:
        others = feats[name].gather(1, order)
        if not obs.absolute and name in ("x", "y", "vx", "vy"):
            others = others - ego[name]
        if name in _INTENTIONS and not obs.observe_intentions:
            others = torch.zeros_like(others)  # to_dict(observe_intentions=False)
        columns.append(torch.cat([ego[name], others], dim=1))
    table = torch.stack(columns, dim=-1)
    if obs.normalize:
        table = _normalize(table, params)
    rows = torch.cat([torch.ones_like(shown[:, :1]), shown], dim=1)
    table = torch.where(rows.unsqueeze(-1), table, torch.zeros_like(table))
    if table.shape[1] < obs.vehicles_count:
        pad = table.new_zeros(v.x.shape[0], obs.vehicles_count - table.shape[1], table.shape[2])
        table = torch.cat([table, pad], dim=1)
    return table


def _normalize(table: torch.Tensor, params: HighwayParams) -> torch.Tensor:
    obs = params.observation
    ranges = dict(obs.features_range)
    columns = list(table.unbind(-1))
    for k, name in enumerate(obs.features):
        if name in ranges:
            low, high = ranges[name]
            value = -1 + (columns[k] - low) * (1 - (-1)) / (high - low)
            columns[k] = torch.clamp(value, -1, 1) if obs.clip else value
    return torch.stack(columns, dim=-1)
