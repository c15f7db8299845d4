"""Straight parallel lanes: lane coordinates, the closest lane, on-lane and reachability.

Lane ``i`` is highway-env's ``StraightLane((0, i * width), (length, i * width))``: its
direction is exactly (1, 0), so a position's longitudinal coordinate is its x and its
lateral coordinate is ``y - i * width``, both as highway-env computes them (its dot
products with the unit axes add exact zeros). The functions follow ``road/lane.py``
operation by operation, so that thresholds flip where highway-env's do.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> road = tensor_params("highway-fast-v0").road
    >>> closest_lane(torch.tensor([50.0]), torch.tensor([5.9]), torch.tensor([0.0]), road)
    tensor([1])
"""

from __future__ import annotations

import math

import torch

from torchrl_grpo.sim.params import RoadParams

__all__ = [
    "closest_lane",
    "is_reachable",
    "lateral",
    "not_zero",
    "on_lane",
    "wrap_to_pi",
]


def not_zero(x: torch.Tensor, eps: float = 1e-2) -> torch.Tensor:
    """highway-env's ``utils.not_zero``: ``x`` if ``|x| > eps``, else ``±eps`` by sign.

    Example:
        >>> not_zero(torch.tensor([0.5, 0.0, -0.001], dtype=torch.float64)).tolist()
        [0.5, 0.01, -0.01]
    """
    # eps in x's own dtype: a Python scalar in torch.where would round it through float32.
    small = torch.full_like(x, eps)
    return torch.where(x.abs() > eps, x, torch.where(x >= 0, small, -small))


def wrap_to_pi(x: torch.Tensor) -> torch.Tensor:
    """``((x + pi) mod 2 pi) - pi``, with a floor modulo, as ``utils.wrap_to_pi``.

    Example:
        >>> round(float(wrap_to_pi(torch.tensor(4.0, dtype=torch.float64))), 6)
        -2.283185
    """
    return torch.remainder(x + math.pi, 2 * math.pi) - math.pi


def lateral(y: torch.Tensor, lane: torch.Tensor, road: RoadParams) -> torch.Tensor:
    """The lateral coordinate of ``y`` in lane ``lane`` (m).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("highway-fast-v0").road
        >>> lateral(torch.tensor([5.0]), torch.tensor([1]), road).tolist()
        [1.0]
    """
    return y - (lane * road.lane_width).to(y.dtype)


def on_lane(
    x: torch.Tensor, y: torch.Tensor, lane: torch.Tensor, road: RoadParams, margin: float = 0.0
) -> torch.Tensor:
    """``lane.on_lane(position, margin=margin)``.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("highway-fast-v0").road
        >>> on_lane(torch.tensor([1.0, 1.0]), torch.tensor([2.0, 2.5]), torch.tensor([0, 0]), road)
        tensor([ True, False])
    """
    lat = lateral(y, lane, road)
    return (
        (lat.abs() <= road.lane_width / 2 + margin)
        & (x >= -road.margin_length)
        & (x < road.lane_length + road.margin_length)
    )


def is_reachable(
    x: torch.Tensor, y: torch.Tensor, lane: torch.Tensor, road: RoadParams
) -> torch.Tensor:
    """``lane.is_reachable_from(position)``: within two lane widths, and along the lane.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("highway-fast-v0").road
        >>> x, y = torch.tensor([1.0, -1.0]), torch.tensor([0.0, 0.0])
        >>> is_reachable(x, y, torch.tensor([2, 0]), road)
        tensor([ True, False])
    """
    lat = lateral(y, lane, road)
    return (
        (lat.abs() <= 2 * road.lane_width) & (x >= 0) & (x < road.lane_length + road.margin_length)
    )


def closest_lane(
    x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor, road: RoadParams
) -> torch.Tensor:
    """``network.get_closest_lane_index(position, heading)``'s lane id (int64).

    The distance of lane ``i`` is ``|lat_i| + max(x - length, 0) + max(-x, 0) +
    |wrap_to_pi(heading)|``, summed in that order, and the first minimum wins, as
    ``np.argmin`` picks it.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("highway-fast-v0").road
        >>> closest_lane(torch.tensor([0.0, 0.0]), torch.tensor([2.0, 9.0]), torch.zeros(2), road)
        tensor([0, 2])
    """
    lanes = torch.arange(road.lanes_count, device=x.device)
    lat = lateral(y.unsqueeze(-1), lanes, road).abs()
    past_end = torch.clamp(x - road.lane_length, min=0).unsqueeze(-1)
    before_start = torch.clamp(0 - x, min=0).unsqueeze(-1)
    angle = wrap_to_pi(heading - 0.0).abs().unsqueeze(-1)
    distance = ((lat + past_end) + before_start) + angle
    return distance.argmin(-1)
