"""The constants of merge-v0: its road graph, its reset, its reward, beside the shared models'.

:class:`MergeParams` has the fields the shared pure functions read of a
:class:`~torchrl_grpo.sim.HighwayParams` (``vehicle``, ``idm``, ``control``, ``time``,
``observation``, ``road.speed_limit``, ``road.lanes_count``,
``traffic.others_check_collisions``), so that IDM, the steering cascade, the
kinematics, the collision test and the state checks serve both scenarios, and the
merge's own: the lane graph (:class:`MergeRoad`), the reset's spawn table
(:class:`MergeTraffic`) and the merging reward (:class:`MergeReward`). Every value is
read from highway-env by :func:`torchrl_grpo.envs.highway.tensor_params`.

The vehicle table of a merge world has ``traffic.vehicles_count + 2`` rows: the ego,
the IDM vehicles in ``road.vehicles`` order (the merging car last), then the obstacle
(``road.objects[0]``), which never acts nor moves.

Example:
    >>> from torchrl_grpo.envs import tensor_params
    >>> params = tensor_params("merge-v0")
    >>> params.num_vehicles, params.obstacle_row, params.road.lanes_count, params.time.frames
    (6, 5, 9, 15)
"""

from __future__ import annotations

from dataclasses import dataclass

from torchrl_grpo.sim.lanes import LaneGeometry
from torchrl_grpo.sim.params import (
    ControlParams,
    IDMParams,
    ObservationParams,
    TimeParams,
    VehicleParams,
)

__all__ = ["MergeParams", "MergeReward", "MergeRoad", "MergeTraffic"]


@dataclass(frozen=True)
class MergeRoad:
    """The merge road: 9 lanes in highway-env's flat order, and their links.

    Attributes:
        lanes: every lane's geometry.
        lane_id: each lane's id within its road (``lane_index[2]``).
        road: each lane's road number (lanes with equal ``lane_index[:2]`` share it).
        left: the lane ``LANE_LEFT`` aims at (``clip(id - 1)`` on the same road).
        right: the lane ``LANE_RIGHT`` aims at.
        side_left: ``side_lanes``' left lane, -1 where there is none.
        side_right: ``side_lanes``' right lane, -1 where there is none.
        next_lane: ``next_lane`` at the lane's end (itself where no road leaves it).
        lanes_count: 9.
        speed_limit: every lane's speed limit (m/s); IDM clips target speeds to it.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("merge-v0").road.next_lane  # the ramp (8) hands over to (b, c, 2)
        (2, 3, 5, 6, 6, 5, 6, 8, 4)
    """

    lanes: LaneGeometry
    lane_id: tuple[int, ...]
    road: tuple[int, ...]
    left: tuple[int, ...]
    right: tuple[int, ...]
    side_left: tuple[int, ...]
    side_right: tuple[int, ...]
    next_lane: tuple[int, ...]
    lanes_count: int
    speed_limit: float


@dataclass(frozen=True)
class MergeTraffic:
    """``MergeEnv._make_vehicles`` and the obstacle of ``_make_road``.

    Attributes:
        vehicles_count: IDM vehicles (the merging car included).
        ego_lane: the ego's lane (flat id).
        ego_s: the ego's longitudinal position on it (m).
        ego_speed: the ego's initial speed (m/s).
        spawn_lanes: the lanes ``integers(2)`` picks from (flat ids).
        spawns: ``(s, speed)`` of each highway IDM vehicle before jitter.
        position_jitter: ``uniform`` bounds added to ``s``.
        speed_jitter: ``uniform`` bounds added to the speed.
        merging_lane: the merging car's lane (flat id).
        merging_s: its longitudinal position (m).
        merging_speed: its initial speed (m/s).
        merging_target_speed: its target speed (m/s).
        delta: IDM's velocity exponent (no ``randomize_behavior`` here).
        obstacle_lane: the obstacle's lane (flat id).
        obstacle_x: the obstacle's position (m).
        obstacle_y: see ``obstacle_x``.
        obstacle_length: its length (m).
        obstacle_width: its width (m).
        others_check_collisions: True: every vehicle checks collisions.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("merge-v0").traffic.obstacle_x
        310.0
    """

    vehicles_count: int
    ego_lane: int
    ego_s: float
    ego_speed: float
    spawn_lanes: tuple[int, ...]
    spawns: tuple[tuple[float, float], ...]
    position_jitter: tuple[float, float]
    speed_jitter: tuple[float, float]
    merging_lane: int
    merging_s: float
    merging_speed: float
    merging_target_speed: float
    delta: float
    obstacle_lane: int
    obstacle_x: float
    obstacle_y: float
    obstacle_length: float
    obstacle_width: float
    others_check_collisions: bool


@dataclass(frozen=True)
class MergeReward:
    """``MergeEnv._rewards``, ``_reward`` and ``_is_terminated``.

    Attributes:
        collision_reward: weight of the crash flag.
        right_lane_reward: weight of the current lane's id.
        high_speed_reward: weight of the speed mapped from ``reward_speed_range``.
        lane_change_reward: weight of a lane-change action.
        merging_speed_reward: weight of the merge lane's summed speed deficits.
        reward_speed_range: speeds mapped to [0, 1] (unclipped).
        merge_lane: the lane whose vehicles' speed deficits count (flat id).
        terminal_x: the episode ends past this x (m).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("merge-v0").reward.merge_lane
        4
    """

    collision_reward: float
    right_lane_reward: float
    high_speed_reward: float
    lane_change_reward: float
    merging_speed_reward: float
    reward_speed_range: tuple[float, float]
    merge_lane: int
    terminal_x: float


@dataclass(frozen=True)
class MergeParams:
    """Everything a batched merge world needs besides its state.

    Attributes:
        road: the lanes and their links.
        vehicle: the bicycle model.
        idm: the IDM and MOBIL constants.
        control: the controllers and the ego's target speeds.
        time: frequencies.
        traffic: the reset's spawn table and the obstacle.
        reward: the reward and the episode's end.
        observation: the Kinematics table (``features_range`` as fixed at reset).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("merge-v0").num_vehicles
        6
    """

    road: MergeRoad
    vehicle: VehicleParams
    idm: IDMParams
    control: ControlParams
    time: TimeParams
    traffic: MergeTraffic
    reward: MergeReward
    observation: ObservationParams

    @property
    def num_vehicles(self) -> int:
        """Rows of the vehicle table: the ego, the IDM vehicles, the obstacle."""
        return self.traffic.vehicles_count + 2

    @property
    def obstacle_row(self) -> int:
        """The obstacle's row (the last)."""
        return self.num_vehicles - 1
