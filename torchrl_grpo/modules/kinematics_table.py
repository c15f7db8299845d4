"""Decoding highway-env's Kinematics observation back into metres and metres per second.

highway-env (1.12.1, ``envs/common/observation.py``) builds the table as follows: row 0
is the ego vehicle in ABSOLUTE coordinates; the other rows are the nearest vehicles,
relative to the ego unless ``absolute=True``; then every column that has a range is
mapped linearly from ``[low, high]`` to ``[-1, 1]`` and clipped; missing rows are zeros
(presence 0). Without a configured ``features_range`` the ranges are filled on the
first observation: x in +-5 * MAX_SPEED, y in +-lane_width * number of lanes, vx and vy
in +-2 * MAX_SPEED.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

__all__ = [
    "DEFAULT_FEATURES",
    "KinematicsLayout",
    "LANE_WIDTH",
    "MAX_SPEED",
    "VEHICLE_LENGTH",
]

#: ``KinematicObservation.FEATURES`` of highway-env.
DEFAULT_FEATURES: tuple[str, ...] = ("presence", "x", "y", "vx", "vy")
#: ``Vehicle.MAX_SPEED`` (m/s), which sets the default x / vx / vy ranges.
MAX_SPEED: float = 40.0
#: ``AbstractLane.DEFAULT_WIDTH`` (m), which sets the default y range.
LANE_WIDTH: float = 4.0
#: ``Vehicle.LENGTH`` (m): positions are vehicle centres, gaps subtract one length.
VEHICLE_LENGTH: float = 5.0

_RELATIVE = ("x", "y", "vx", "vy")


@dataclass(frozen=True)
class KinematicsLayout:
    """How a Kinematics observation table is laid out and normalised.

    Args:
        features: column names, in order (highway-env's ``features``).
        features_range: ``{feature: (low, high)}`` as configured; ``None`` means
            highway-env's lazily computed defaults (see the module docstring).
        normalize: whether columns were mapped to [-1, 1].
        absolute: whether other vehicles are in absolute coordinates.
        lanes_count: number of lanes; sets the default y range and which lanes exist.
        n_vehicles: number of rows (the observation's ``vehicles_count``).
        lane_width: lane width in metres.

    Example:
        >>> layout = KinematicsLayout.from_highway_config(
        ...     {"observation": {"type": "Kinematics"}, "lanes_count": 3})
        >>> obs = torch.tensor([[1.0, 0.1, 1 / 3, 0.3125, 0.0],
        ...                     [1.0, 0.1, 0.0, -0.05, 0.0]])
        >>> cols = layout.decode(obs)
        >>> [round(v, 2) for v in cols["y"].tolist()], [round(v, 1) for v in cols["vx"].tolist()]
        ([4.0, 0.0], [25.0, -4.0])
    """

    features: tuple[str, ...] = DEFAULT_FEATURES
    features_range: Mapping[str, tuple[float, float]] | None = None
    normalize: bool = True
    absolute: bool = False
    lanes_count: int = 3
    n_vehicles: int = 5
    lane_width: float = LANE_WIDTH
    _ranges: dict[str, tuple[float, float]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "features", tuple(self.features))
        if len(set(self.features)) != len(self.features):
            raise ValueError(f"Duplicate features in {self.features}.")
        if self.features_range is None:
            ranges = {
                "x": (-5.0 * MAX_SPEED, 5.0 * MAX_SPEED),
                "y": (-self.lane_width * self.lanes_count, self.lane_width * self.lanes_count),
                "vx": (-2.0 * MAX_SPEED, 2.0 * MAX_SPEED),
                "vy": (-2.0 * MAX_SPEED, 2.0 * MAX_SPEED),
            }
        else:
            # highway-env uses a configured features_range as given, with no defaults.
            ranges = {k: (float(v[0]), float(v[1])) for k, v in self.features_range.items()}
        object.__setattr__(self, "_ranges", ranges)

    @classmethod
    def from_highway_config(
        cls, config: Mapping[str, Any], lanes_count: int | None = None
    ) -> KinematicsLayout:
        """Builds the layout from a highway-env config (``env.unwrapped.config``).

        Args:
            config: the env config (with an ``"observation"`` entry), or the
                observation config alone.
            lanes_count: overrides ``config["lanes_count"]`` (needed when only the
                observation config is given and the road does not have 3 lanes).

        Returns:
            The layout.

        Raises:
            ValueError: if the observation type is not Kinematics.
        """
        obs_config = config.get("observation", config)
        obs_type = obs_config.get("type", "Kinematics")
        if obs_type != "Kinematics":
            raise ValueError(f"Only the Kinematics observation is supported, got {obs_type!r}.")
        if lanes_count is None:
            lanes_count = int(config.get("lanes_count", 3))
        features_range = obs_config.get("features_range")
        return cls(
            features=tuple(obs_config.get("features") or DEFAULT_FEATURES),
            features_range=None if not features_range else dict(features_range),
            normalize=bool(obs_config.get("normalize", True)),
            absolute=bool(obs_config.get("absolute", False)),
            lanes_count=lanes_count,
            n_vehicles=int(obs_config.get("vehicles_count", 5)),
        )

    @property
    def n_features(self) -> int:
        """Number of columns of the table."""
        return len(self.features)

    def index(self, feature: str) -> int:
        """Column index of ``feature``."""
        try:
            return self.features.index(feature)
        except ValueError:
            raise KeyError(f"Feature {feature!r} is not observed ({self.features}).") from None

    def require(self, features: Sequence[str]) -> None:
        """Raises ``ValueError`` unless every feature in ``features`` is observed."""
        missing = [f for f in features if f not in self.features]
        if missing:
            raise ValueError(f"Features {missing} are needed but not observed ({self.features}).")

    def decode(self, observation: torch.Tensor) -> dict[str, torch.Tensor]:
        """Undoes the normalisation and makes other vehicles relative to the ego.

        Args:
            observation: ``[*batch, V, F]`` table.

        Returns:
            ``{feature: [*batch, V]}`` in physical units. Row 0 (the ego) keeps its
            absolute values; rows 1+ of x, y, vx, vy are relative to the ego whatever
            ``absolute`` was. Values clipped by highway-env stay clipped (e.g. the ego's
            absolute x beyond 200 m).
        """
        if observation.shape[-1] != self.n_features:
            raise ValueError(
                f"Expected {self.n_features} features {self.features}, got shape "
                f"{tuple(observation.shape)}."
            )
        columns = {}
        for i, name in enumerate(self.features):
            col = observation[..., i]
            if self.normalize and name in self._ranges:
                low, high = self._ranges[name]
                col = low + (col + 1.0) * (high - low) / 2.0
            columns[name] = col
        if self.absolute:
            for name in _RELATIVE:
                if name in columns:
                    col = columns[name]
                    others = col[..., 1:] - col[..., :1]
                    columns[name] = torch.cat([col[..., :1], others], dim=-1)
        return columns

    def encode(self, columns: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Builds an observation table from physical values, as highway-env would.

        The inverse of :meth:`decode` (up to clipping), handy to hand-build scenes.

        Args:
            columns: ``{feature: [*batch, V]}`` for every feature, with the ego
                absolute in row 0 and the other rows relative to it.

        Returns:
            The ``[*batch, V, F]`` float32 table, normalised and clipped.

        Example:
            >>> layout = KinematicsLayout()
            >>> cols = {f: torch.zeros(2) for f in layout.features}
            >>> cols["vx"] = torch.tensor([25.0, -4.0])
            >>> [round(v, 4) for v in layout.encode(cols)[:, 3].tolist()]
            [0.3125, -0.05]
        """
        missing = [f for f in self.features if f not in columns]
        if missing:
            raise ValueError(f"Columns {missing} are missing.")
        out = []
        for name in self.features:
            col = torch.as_tensor(columns[name], dtype=torch.float32)
            if self.absolute and name in _RELATIVE:
                col = torch.cat([col[..., :1], col[..., 1:] + col[..., :1]], dim=-1)
            if self.normalize and name in self._ranges:
                low, high = self._ranges[name]
                col = (2.0 * (col - low) / (high - low) - 1.0).clamp(-1.0, 1.0)
            out.append(col)
        return torch.stack(out, dim=-1)
