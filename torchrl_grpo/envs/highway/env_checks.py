"""The rules a highway-env state's env-level entries obey: checked before a restore writes.

:class:`~torchrl_grpo.envs.highway.env_fields.EnvFields` reads a state's env-level
entries back; the checks here refuse what highway-env could not step (a NaN clock,
an IDM constant that makes its desired gap NaN, a controlled vehicle that is a wall,
a goal observation of a vehicle without a goal) with a
:class:`~torchrl_grpo.envs.StateCorruptedError` that names the entry, and admit
everything highway-env can reach.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from torchrl_grpo.envs.core.errors import StateCorruptedError
from torchrl_grpo.envs.highway.layout import NONE, VEHICLE
from torchrl_grpo.envs.highway.schema import CLASS_PARAMETER_DOMAINS, MAX_MAGNITUDE

__all__ = [
    "check_class_parameters",
    "check_features_range",
    "check_magnitude",
    "check_observed_goal",
    "vehicle_in_slot",
]


def check_magnitude(where: str, values: torch.Tensor) -> None:
    """Refuse NaN, inf and magnitudes beyond :data:`~.schema.MAX_MAGNITUDE` in ``values``.

    Example:
        >>> check_magnitude("env.time", torch.tensor([1.5], dtype=torch.float64))
        >>> try:
        ...     check_magnitude("env.time", torch.tensor([float("nan")], dtype=torch.float64))
        ... except StateCorruptedError as err:
        ...     print(err)
        env.time holds nan: not finite, or beyond 1e+09
    """
    bad = ~(values.abs() <= MAX_MAGNITUDE)  # NaN fails the comparison
    if bool(bad.any()):
        raise StateCorruptedError(
            f"{where} holds {values[bad][0].item()}: not finite, or beyond {MAX_MAGNITUDE:g}"
        )


def vehicle_in_slot(code: int, where: str, by_slot: dict[int, Any], kinds: Sequence[int]) -> Any:
    """The vehicle an env-level reference (``env.controlled``, ...) points at, or ``None``.

    A controlled, acted-on or observing vehicle must be in ``road.vehicles``: one in an
    object slot (an Obstacle, a Landmark) has no ``act`` and is never stepped.

    Args:
        code: the stored slot (``-1``: none).
        where: the entry, named in errors.
        by_slot: the decoded objects by slot.
        kinds: the kind column of the entity table (``0``: a vehicle slot).

    Raises:
        StateCorruptedError: the slot is empty or not a vehicle slot.

    Example:
        >>> vehicle_in_slot(-1, "env.controlled", {}, [])  # none
        >>> vehicle_in_slot(0, "env.controlled", {0: "car"}, [0])
        'car'
        >>> try:
        ...     vehicle_in_slot(1, "env.controlled", {0: "car", 1: "wall"}, [0, 1])
        ... except StateCorruptedError as err:
        ...     print(err)
        env.controlled refers to slot 1, a str in an object slot (kind 1), not a vehicle
    """
    if code == NONE:
        return None
    if code not in by_slot:
        raise StateCorruptedError(f"{where} refers to empty slot {code}")
    obj = by_slot[code]
    kind = int(kinds[code])
    if kind != VEHICLE:
        raise StateCorruptedError(
            f"{where} refers to slot {code}, a {type(obj).__qualname__} in an object slot "
            f"(kind {kind}), not a vehicle"
        )
    return obj


def check_observed_goal(observer: Any, where: str, slot_of: dict[int, int]) -> None:
    """Refuse a goal observation of a vehicle that holds no goal (parking-v0).

    highway-env's ``KinematicsGoalObservation`` reads ``observer.goal.to_dict()``
    at every step; any road object serves as a goal, no observer (``None``) is
    observed as zeros.

    Args:
        observer: the observed vehicle (``None``: none).
        where: what observes it, named in errors.
        slot_of: entity slot by object id (named in errors).

    Raises:
        StateCorruptedError: the observer has no ``goal``, or a ``None`` one.

    Example:
        >>> class Car:
        ...     pass
        >>> car = Car()
        >>> car.goal = Car()
        >>> check_observed_goal(car, "the observation", {id(car): 0})
        >>> del car.goal
        >>> try:
        ...     check_observed_goal(car, "the observation", {id(car): 0})
        ... except StateCorruptedError as err:
        ...     print(err)
        entities.goal of slot 0 is absent, but the observation observes its goal
    """
    if observer is None:
        return
    goal = vars(observer).get("goal")
    if goal is None:
        state = "None" if "goal" in vars(observer) else "absent"
        raise StateCorruptedError(
            f"entities.goal of slot {slot_of.get(id(observer))} is {state}, but {where} "
            "observes its goal"
        )


def check_class_parameters(class_parameters: list[tuple[type, str]], values: list[float]) -> None:
    """Refuse class constants outside their domain (:data:`~.schema.CLASS_PARAMETER_DOMAINS`).

    Example:
        >>> from highway_env.vehicle.behavior import IDMVehicle
        >>> check_class_parameters([(IDMVehicle, "COMFORT_ACC_MAX")], [3.0])
        >>> try:
        ...     check_class_parameters([(IDMVehicle, "COMFORT_ACC_MAX")], [0.0])
        ... except StateCorruptedError as err:
        ...     print(err)
        env.class_params: IDMVehicle.COMFORT_ACC_MAX is 0.0, outside (0.0, inf)
    """
    for (cls, name), value in zip(class_parameters, values, strict=True):
        low, high = CLASS_PARAMETER_DOMAINS.get((cls, name), (-math.inf, math.inf))
        if not low < value < high:
            raise StateCorruptedError(
                f"env.class_params: {cls.__qualname__}.{name} is {value}, outside ({low}, {high})"
            )


def check_features_range(features_range: dict[str, list[float]] | None) -> None:
    """Refuse an observation ``features_range`` whose low end is not below its high end.

    Example:
        >>> check_features_range({"x": [-100.0, 100.0]})
        >>> try:
        ...     check_features_range({"x": [5.0, 5.0]})
        ... except StateCorruptedError as err:
        ...     print(err)
        env.features_range: x (set in env.features_range_mask) spans [5.0, 5.0]
    """
    for key, (low, high) in (features_range or {}).items():
        if not low < high:
            raise StateCorruptedError(
                f"env.features_range: {key} (set in env.features_range_mask) spans [{low}, {high}]"
            )
