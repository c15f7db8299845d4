"""lane-keeping-v0's env-level extras in a highway-env state: its lanes and trajectory.

lane-keeping-v0 keeps the lane its vehicle follows (``env.lane``), the lanes still
ahead (``env.lanes``) and the trajectory it has driven (``env.trajectory``, a list
that grows every step) on the env itself, not on a road object.
:class:`~torchrl_grpo.envs.highway.env_fields.EnvFields` stores them through
:class:`LaneKeepingFields`; in other scenarios the entries are empty placeholders, so
that every state has the same keys.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torchrl.data import Unbounded

from torchrl_grpo.envs.core.errors import SnapshotError, StateCapacityError, StateCorruptedError
from torchrl_grpo.envs.core.gym_state import time_limit
from torchrl_grpo.envs.highway.env_checks import check_magnitude
from torchrl_grpo.envs.highway.layout import NONE, EntityLayout

__all__ = ["LaneKeepingFields", "lane_index_of"]

MAX_LANES = 4  # lanes ahead a state holds (lane-keeping-v0 queues 2)
_NO_LANE = NONE - 1  # the lane code of an env without an env-level lane


class LaneKeepingFields:
    """Encodes and restores ``lane``, ``lanes`` and ``trajectory`` of a lane-keeping env.

    Args:
        env: the freshly reset env the codec binds to.
        layout: the codec's entity layout (for lane codes).
        max_trajectory: rows kept of ``trajectory`` (``None``: the TimeLimit plus 8).

    Example:
        >>> import gymnasium as gym
        >>> import highway_env  # noqa: F401 - registers the scenarios
        >>> from torchrl_grpo.envs.highway.highway_codec import HighwayStateCodec
        >>> env = gym.make("lane-keeping-v0")
        >>> _ = env.reset(seed=0)
        >>> codec = HighwayStateCodec()
        >>> codec.bind(env)
        >>> extras = codec.env_fields.lane_keeping
        >>> out = extras.encode(env)
        >>> int(out["env", "lanes_len"]), out["env", "trajectory"].shape
        (1, (208, 6))
    """

    def __init__(
        self, env: gym.Env, layout: EntityLayout, max_trajectory: int | None = None
    ) -> None:
        core = env.unwrapped
        self.layout = layout
        self.has_lane = hasattr(core, "lane")
        self.has_lanes = hasattr(core, "lanes")
        self.has_trajectory = hasattr(core, "trajectory")
        limit = time_limit(env)
        self.max_trajectory = max_trajectory or (limit + 8 if limit else 1024)

    def spec(self) -> dict[str, Unbounded]:
        """The entries' specs (the trajectory's floats in float64; the codec stores bits)."""
        rows = self.max_trajectory if self.has_trajectory else 0
        return {
            "lane": Unbounded((3,), dtype=torch.int64),
            "lanes": Unbounded((MAX_LANES, 3), dtype=torch.int64),
            "lanes_len": Unbounded((), dtype=torch.int64),
            "trajectory": Unbounded((rows, 6), dtype=torch.float64),
            "trajectory_len": Unbounded((), dtype=torch.int64),
        }

    def encode(self, env: gym.Env) -> dict[tuple[str, str], np.ndarray]:
        """The entries' arrays of ``env``'s state."""
        core = env.unwrapped
        network = core.road.network
        lane = np.full(3, _NO_LANE, dtype=np.int64)
        if self.has_lane and core.lane is not None:
            lane[:] = self.layout.lane_code(lane_index_of(network, core.lane))
        lanes = np.zeros((MAX_LANES, 3), dtype=np.int64)
        lane_list = core.lanes if self.has_lanes else []
        if len(lane_list) > MAX_LANES:
            raise StateCapacityError(f"{len(lane_list)} lanes ahead, the state holds {MAX_LANES}")
        for j, each in enumerate(lane_list):
            lanes[j] = self.layout.lane_code(lane_index_of(network, each))
        rows = self.max_trajectory if self.has_trajectory else 0
        trajectory = np.zeros((rows, 6))
        points = core.trajectory if self.has_trajectory else []
        if len(points) > rows:
            raise StateCapacityError(
                f"the trajectory holds {len(points)} points, the state pads to {rows}: "
                "build the env with a larger max_trajectory"
            )
        if points:
            trajectory[: len(points)] = np.asarray(points).reshape(len(points), 6)
        if getattr(core, "interval_trajectory", None):
            raise SnapshotError("lane-keeping interval trajectories are not supported")
        return {
            ("env", "lane"): lane,
            ("env", "lanes"): lanes,
            ("env", "lanes_len"): np.asarray(len(lane_list), dtype=np.int64),
            ("env", "trajectory"): trajectory,
            ("env", "trajectory_len"): np.asarray(len(points), dtype=np.int64),
        }

    def decode(self, core: Any, t: dict[Any, torch.Tensor]) -> dict[str, Any]:
        """Check the entries of ``t`` and build what a restore writes (nothing written)."""
        n_points = t[("env", "trajectory_len")].item()
        trajectory = t[("env", "trajectory")]
        if not 0 <= n_points <= trajectory.shape[0]:
            raise StateCorruptedError(f"env.trajectory_len is {n_points}")
        points = trajectory[:n_points].view(torch.float64)
        check_magnitude("env.trajectory", points)
        lane_code = t[("env", "lane")].tolist()
        lane = None if lane_code[0] == _NO_LANE else self.lane_object(core, lane_code, "env.lane")
        if lane is None and self.has_lane:
            # Reset sets it and no step clears it: its reward reads it every step.
            raise StateCorruptedError(
                f"env.lane is {lane_code}, no lane, but lane-keeping-v0 always follows one"
            )
        n_lanes = t[("env", "lanes_len")].item()
        if not 0 <= n_lanes <= MAX_LANES:
            raise StateCorruptedError(f"env.lanes_len is {n_lanes}")
        where = f"env.lanes (of env.lanes_len {n_lanes})"
        return {
            "lane": lane,
            "lanes": [
                self.lane_object(core, c, where) for c in t[("env", "lanes")].tolist()[:n_lanes]
            ],
            "trajectory": [p.reshape(6, 1).copy() for p in points.numpy()],
        }

    def lane_object(self, core: Any, code: list[int], where: str) -> Any:
        """The lane object of a stored lane code (``where`` names the entry in errors)."""
        index = self.layout.lane_index(code, where)
        try:
            return core.road.network.get_lane(index)
        except (KeyError, IndexError) as err:
            raise StateCorruptedError(f"{where}: lane {index} is not on this road") from err

    def commit(self, core: Any, plan: dict[str, Any]) -> None:
        """Write a decoded plan's entries into the unwrapped env ``core`` (cannot fail)."""
        if self.has_lane:
            core.lane = plan["lane"]
        if self.has_lanes:
            core.lanes = plan["lanes"]
        if self.has_trajectory:
            core.trajectory = plan["trajectory"]


def lane_index_of(network: Any, lane: Any) -> tuple:
    """The ``(from, to, id)`` index of a lane object of ``network``.

    Example:
        >>> from highway_env.road.road import RoadNetwork
        >>> net = RoadNetwork.straight_road_network(2)
        >>> lane_index_of(net, net.get_lane(("0", "1", 1)))
        ('0', '1', 1)
    """
    for start, destinations in network.graph.items():
        for end, lanes in destinations.items():
            for lane_id, candidate in enumerate(lanes):
                if candidate is lane:
                    return (start, end, lane_id)
    raise SnapshotError("an env-level lane is not part of the road network")
