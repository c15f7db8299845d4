"""highway-env's Kinematics observation, the same bits without pandas.

``KinematicObservation.observe`` builds a pandas DataFrame from the observed vehicles'
dicts, normalises and clips its columns, pads it and reads it back: on highway-fast-v0
and merge-v0 that is 3 to 4 ms of a 10 to 16 ms step, most of it pandas' own
overhead on a 5 x 5 table. :class:`FastKinematicObservation` does the same arithmetic
on a float64 numpy array: the same dicts (``Vehicle.to_dict``), the same ``lmap``
expression evaluated in the same order, the same clip, padding, shuffle draw and
float32 cast, so every observation is bitwise the one highway-env computes (checked
against it step by step in ``tests/envs/test_fast_observation.py``), in a tenth of
the time.

highway-env rebuilds its observation object on every reset (``define_spaces``), so
:func:`use_fast_kinematics` is called before each step: it swaps the class of a plain
``KinematicObservation`` (never a subclass, which may observe differently) and leaves
every other observation type alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from highway_env.envs.common.observation import KinematicObservation
from highway_env.road.lane import AbstractLane
from highway_env.vehicle.kinematics import Vehicle

__all__ = ["FastKinematicObservation", "use_fast_kinematics"]


class FastKinematicObservation(KinematicObservation):
    """``KinematicObservation`` whose :meth:`observe` builds a numpy table instead of pandas'.

    Example:
        >>> import gymnasium as gym
        >>> env = gym.make("highway-fast-v0")
        >>> _ = env.reset(seed=0)
        >>> _ = env.step(1)
        >>> observer = env.unwrapped.observation_type
        >>> slow = KinematicObservation.observe(observer)
        >>> use_fast_kinematics(env.unwrapped)
        True
        >>> fast = env.unwrapped.observation_type.observe()
        >>> fast.dtype, fast.tobytes() == slow.tobytes()
        (dtype('float32'), True)
    """

    def observe(self) -> np.ndarray:
        """The observation ``[vehicles_count, len(features)]``, float32."""
        if not self.env.road:
            return np.zeros(self.space().shape)
        ego = self.observer_vehicle
        rows = [ego.to_dict()]
        close = self.env.road.close_objects_to(
            ego,
            self.env.PERCEPTION_DISTANCE,
            count=self.vehicles_count - 1,
            see_behind=self.see_behind,
            sort=self.order == "sorted",
            vehicles_only=not self.include_obstacles,
        )
        if close:
            origin = ego if not self.absolute else None
            rows += [
                v.to_dict(origin, observe_intentions=self.observe_intentions)
                for v in close[-self.vehicles_count + 1 :]
            ]
        table = _table(rows, self.features)
        if self.normalize:
            _normalize(self, table)
        obs = np.zeros((max(self.vehicles_count, len(rows)), len(self.features)))
        obs[: len(rows)] = table
        if self.order == "shuffled":
            self.env.np_random.shuffle(obs[1:])
        return obs.astype(self.space().dtype)


def _normalize(observer: KinematicObservation, table: np.ndarray) -> None:
    """Map each ranged feature of ``table`` to [-1, 1] in place (clipped with ``clip``)."""
    if not observer.features_range:
        # highway-env's default ranges, fixed at the first observation as it does.
        lane_index = observer.observer_vehicle.lane_index
        width = AbstractLane.DEFAULT_WIDTH * len(
            observer.env.road.network.all_side_lanes(lane_index)
        )
        observer.features_range = {
            "x": [-5.0 * Vehicle.MAX_SPEED, 5.0 * Vehicle.MAX_SPEED],
            "y": [-width, width],
            "vx": [-2 * Vehicle.MAX_SPEED, 2 * Vehicle.MAX_SPEED],
            "vy": [-2 * Vehicle.MAX_SPEED, 2 * Vehicle.MAX_SPEED],
        }
    for feature, (low, high) in observer.features_range.items():
        if feature in observer.features:
            column = observer.features.index(feature)
            # highway_env.utils.lmap's expression, in its order of operations.
            value = -1 + (table[:, column] - low) * (1 - -1) / (high - low)
            table[:, column] = np.clip(value, -1, 1) if observer.clip else value


def _table(rows: list[dict[str, Any]], features: Sequence[str]) -> np.ndarray:
    """The ``features`` of each row as float64; a feature some rows lack is NaN there.

    Raises:
        KeyError: a feature no row has (pandas' error for a missing column).
    """
    missing = [f for f in features if all(f not in row for row in rows)]
    if missing:
        raise KeyError(f"{missing} not in the observed vehicles' features")
    return np.array([[row.get(f, np.nan) for f in features] for row in rows], dtype=np.float64)


def use_fast_kinematics(core: Any) -> bool:
    """Give ``core``'s plain Kinematics observation the fast :meth:`observe`.

    Args:
        core: a highway-env env (``gym_env.unwrapped``).

    Returns:
        Whether its observation is now a :class:`FastKinematicObservation`.
    """
    observer = getattr(core, "observation_type", None)
    if type(observer) is KinematicObservation:
        observer.__class__ = FastKinematicObservation
    return type(observer) is FastKinematicObservation
