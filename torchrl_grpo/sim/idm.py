"""The Intelligent Driver Model, as ``IDMVehicle.acceleration`` and ``desired_gap`` compute it.

``acceleration(ego, front) = free - interaction``: the free-road term
``a (1 - (max(v, 0) / |v0|) ** delta)`` (:func:`free_road`) and the interaction term
``a (gap / distance) ** 2`` (:func:`interaction`), computed separately so that a
substep evaluates each vehicle's free-road term once and MOBIL reuses it. The
exponent ``delta`` is the one of the vehicle that DECIDES: highway-env evaluates
other vehicles' accelerations with the deciding vehicle's own ``DELTA`` (MOBIL does
so for the new follower). Pairs are gathered as :class:`Car` tensors of one shape.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> params = tensor_params("highway-fast-v0")
    >>> z = torch.tensor([0.0])
    >>> ego = Car(z, torch.tensor([20.0]), z + 1, z, torch.tensor([25.0]))
    >>> round(float(free_road(ego, torch.tensor([4.0]), params)), 4)  # 3 (1 - (20 / 25) ** 4)
    1.7712
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.road import not_zero
from torchrl_grpo.sim.state import take

__all__ = ["Car", "acceleration", "desired_gap", "free_road", "gather_car", "interaction"]


class Car(NamedTuple):
    """The fields of a vehicle that IDM reads, gathered for a batch of queries.

    Attributes:
        x: position along the road.
        speed: speed.
        cos_h: cosine of the heading.
        sin_h: sine of the heading.
        target_speed: speed set-point.
        exists: whether there is a vehicle (``None``: always).
    """

    x: torch.Tensor
    speed: torch.Tensor
    cos_h: torch.Tensor
    sin_h: torch.Tensor
    target_speed: torch.Tensor
    exists: torch.Tensor | None = None


def gather_car(table: Car, rows: torch.Tensor, index: torch.Tensor) -> Car:
    """The :class:`Car` at vehicle ``index`` of world ``rows`` (index -1: no vehicle).

    Args:
        table: a :class:`Car` of ``[B, N]`` tensors (every vehicle of every world).
        rows: ``[Q]`` worlds.
        index: ``[Q]`` vehicle indices, -1 for none.

    Returns:
        A :class:`Car` of ``[Q]`` tensors.

    Example:
        >>> z = torch.tensor([[1.0, 2.0]])
        >>> car = gather_car(Car(z, z, z, z, z), torch.tensor([0, 0]), torch.tensor([1, -1]))
        >>> car.x.tolist(), car.exists.tolist()
        ([2.0, 1.0], [True, False])
    """
    at = rows * table.x.shape[1] + index.clamp(min=0)
    return Car(*(take(t, at) for t in table[:5]), exists=index >= 0)


def desired_gap(ego: Car, front: Car, params: HighwayParams) -> torch.Tensor:
    """``d0 + v T + v dv / (2 sqrt(a b))``, with ``dv`` the closing speed along the ego's heading.

    ``dv = (v_ego - v_front) . dir_ego`` is summed plainly, as ``np.dot`` on two
    floats computes it on CPUs whose BLAS does not fuse the multiply-add (see
    docs/sim.md on where bit-exactness holds).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> z = torch.tensor([0.0])
        >>> a = Car(z, torch.tensor([20.0]), z + 1, z, z)
        >>> b = Car(z, torch.tensor([15.0]), z + 1, z, z)
        >>> round(float(desired_gap(a, b, params)), 4)  # 10 + 1.5 * 20 + 20 * 5 / (2 sqrt 15)
        52.9099
    """
    idm = params.idm
    ab = -idm.comfort_acc_max * idm.comfort_acc_min
    dvx = ego.speed * ego.cos_h - front.speed * front.cos_h
    dvy = ego.speed * ego.sin_h - front.speed * front.sin_h
    dv = dvx * ego.cos_h + dvy * ego.sin_h
    return (idm.distance_wanted + ego.speed * idm.time_wanted) + ego.speed * dv / (
        2 * math.sqrt(ab)
    )


def free_road(ego: Car, delta: torch.Tensor, params: HighwayParams) -> torch.Tensor:
    """IDM's free-road acceleration of ``ego`` with exponent ``delta`` (0 where no ego).

    The target speed is clipped to ``[0, speed_limit]`` first, as highway-env does on
    lanes with a speed limit.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> z = torch.tensor([0.0])
        >>> car = Car(z, torch.tensor([30.0]), z + 1, z, torch.tensor([30.0]))
        >>> float(free_road(car, torch.tensor([4.0]), params))
        0.0
    """
    target = torch.clamp(ego.target_speed, 0, params.road.speed_limit)
    ratio = torch.clamp(ego.speed, min=0) / not_zero(target).abs()
    acc = params.idm.comfort_acc_max * (1 - torch.pow(ratio, delta))
    return acc if ego.exists is None else torch.where(ego.exists, acc, torch.zeros_like(acc))


def interaction(ego: Car, front: Car, params: HighwayParams) -> torch.Tensor:
    """IDM's braking term of ``ego`` behind ``front`` (0 where either is missing).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> z = torch.tensor([0.0])
        >>> ego = Car(z, torch.tensor([20.0]), z + 1, z, z)
        >>> front = Car(torch.tensor([30.0]), torch.tensor([20.0]), z + 1, z, z)
        >>> round(float(interaction(ego, front, params)), 4)  # 3 (40 / 30) ** 2
        5.3333
    """
    term = desired_gap(ego, front, params) / not_zero(front.x - ego.x)
    value = params.idm.comfort_acc_max * (term * term)
    for car in (ego, front):
        if car.exists is not None:
            value = torch.where(car.exists, value, torch.zeros_like(value))
    return value


def acceleration(
    ego: Car, front: Car | None, delta: torch.Tensor, params: HighwayParams
) -> torch.Tensor:
    """IDM's acceleration command of ``ego`` behind ``front``, decided with exponent ``delta``.

    Args:
        ego: the follower (``exists`` False gives 0, as for ``ego_vehicle=None``).
        front: the vehicle in front, or ``None`` / ``exists`` False for a free road.
        delta: the deciding vehicle's velocity exponent.
        params: the model's constants.

    Returns:
        The acceleration (m/s^2), unclipped.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> z = torch.tensor([0.0])
        >>> ego = Car(z, torch.tensor([20.0]), z + 1, z, torch.tensor([20.0]))
        >>> front = Car(torch.tensor([30.0]), torch.tensor([20.0]), z + 1, z, z)
        >>> round(float(acceleration(ego, front, torch.tensor([4.0]), params)), 4)  # -3 (40/30)^2
        -5.3333
    """
    acc = free_road(ego, delta, params)
    if front is None:
        return acc
    return acc - interaction(ego, front, params)
