"""The rules a highway-env state's env-level entries obey: checked before a restore writes.

:class:`~torchrl_grpo.envs.highway.env_fields.EnvFields` reads a state's env-level
entries back; the checks here refuse what highway-env could not step (a NaN clock,
an IDM constant that makes its desired gap NaN) with a
:class:`~torchrl_grpo.envs.StateCorruptedError` that names the entry, and admit
everything highway-env can reach.
"""

from __future__ import annotations

import math

import torch

from torchrl_grpo.envs.core.errors import StateCorruptedError
from torchrl_grpo.envs.highway.schema import CLASS_PARAMETER_DOMAINS, MAX_MAGNITUDE

__all__ = [
    "check_class_parameters",
    "check_features_range",
    "check_magnitude",
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
