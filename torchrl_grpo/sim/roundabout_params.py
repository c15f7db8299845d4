"""The constants of roundabout-v0: its road graph with routes, its reset, its reward.

:class:`RoundaboutParams` has the fields the shared pure functions read (``vehicle``,
``idm``, ``control``, ``time``, ``observation``, ``road.lanes`` and the lane links the
merge step reads), and the roundabout's own: the roads and the shortest paths between
them (:class:`RoundaboutRoad`), the reset's spawn table (:class:`RoundaboutTraffic`)
and the reward (:class:`RoundaboutReward`). Every value is read from highway-env by
:func:`torchrl_grpo.envs.highway.tensor_params`.

A route is ``ControlledVehicle.route``: a list of legs ``(from, to, id)``; the first
leg is the lane the vehicle was created on, the others a shortest path's roads with
``id`` None. Each leg is one integer code (:mod:`.routes`): a flat lane id below
``road.lanes_count``, ``lanes_count + road`` for a road whose lane is chosen on the way.

Example:
    >>> from torchrl_grpo.envs import tensor_params
    >>> params = tensor_params("roundabout-v0")
    >>> params.num_vehicles, params.road.lanes_count, params.road.roads_count
    (5, 32, 24)
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

__all__ = ["RoundaboutParams", "RoundaboutReward", "RoundaboutRoad", "RoundaboutTraffic"]


@dataclass(frozen=True)
class RoundaboutRoad:
    """The roundabout's 32 lanes in highway-env's flat order, its 24 roads and their paths.

    Attributes:
        lanes: every lane's geometry.
        lane_id: each lane's id within its road (``lane_index[2]``).
        road: each lane's road number (the order roads first appear in the flat order).
        left: the lane ``LANE_LEFT`` aims at (``clip(id - 1)`` on the same road).
        right: the lane ``LANE_RIGHT`` aims at.
        side_left: ``side_lanes``' left lane, -1 where there is none.
        side_right: ``side_lanes``' right lane, -1 where there is none.
        lanes_count: 32.
        speed_limit: every lane's speed limit (m/s); IDM clips target speeds to it.
        road_from: each road's start node (a number per node name).
        road_to: each road's end node.
        road_lanes: each road's flat lanes by id, -1 padded.
        next_roads: the roads leaving each road's end node, in the graph's order, -1 padded.
        destinations: the node names routes are planned to (the ego's first).
        paths: ``paths[road][d]``: the roads of ``shortest_path(road's end, destinations[d])``.
        route_length: the legs a route can hold.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("roundabout-v0").road
        >>> road.route_codes, road.route_length
        (56, 11)
    """

    lanes: LaneGeometry
    lane_id: tuple[int, ...]
    road: tuple[int, ...]
    left: tuple[int, ...]
    right: tuple[int, ...]
    side_left: tuple[int, ...]
    side_right: tuple[int, ...]
    lanes_count: int
    speed_limit: float
    road_from: tuple[int, ...]
    road_to: tuple[int, ...]
    road_lanes: tuple[tuple[int, ...], ...]
    next_roads: tuple[tuple[int, ...], ...]
    destinations: tuple[str, ...]
    paths: tuple[tuple[tuple[int, ...], ...], ...]
    route_length: int

    @property
    def roads_count(self) -> int:
        """The number of roads."""
        return len(self.road_from)

    @property
    def route_codes(self) -> int:
        """Leg codes run over ``[0, lanes_count + roads_count)``."""
        return self.lanes_count + self.roads_count


@dataclass(frozen=True)
class RoundaboutTraffic:
    """``RoundaboutEnv._make_vehicles``: where each vehicle starts, before its normal draws.

    Attributes:
        vehicles_count: IDM vehicles.
        ego_lane: the ego's spawn lane (flat id).
        ego_s: its longitudinal position (m).
        ego_speed: its initial speed (m/s).
        ego_heading: its initial heading (rad).
        ego_destination: the index in ``road.destinations`` of the ego's route's end.
        spawn_lanes: each IDM vehicle's lane (flat id) before the closest-lane rule.
        spawn_s: each one's longitudinal position before ``position_scale * normal()``.
        position_scale: the normal draw's scale on positions (m).
        spawn_speed: each one's speed before ``speed_scale * normal()``.
        speed_scale: the normal draw's scale on speeds (m/s).
        destinations: the indices in ``road.destinations`` of ``choice``'s options.
        others_check_collisions: True: every vehicle checks collisions.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("roundabout-v0").traffic.spawn_s
        (5.0, 20.0, -20.0, 50.0)
    """

    vehicles_count: int
    ego_lane: int
    ego_s: float
    ego_speed: float
    ego_heading: float
    ego_destination: int
    spawn_lanes: tuple[int, ...]
    spawn_s: tuple[float, ...]
    position_scale: float
    spawn_speed: float
    speed_scale: float
    destinations: tuple[int, ...]
    others_check_collisions: bool


@dataclass(frozen=True)
class RoundaboutReward:
    """``RoundaboutEnv._reward``, ``_is_terminated`` and ``_is_truncated``.

    Attributes:
        collision_reward: weight of the crash flag.
        high_speed_reward: weight of ``speed_index / speed_levels``.
        lane_change_reward: weight of a lane-change action.
        on_road_reward: weight of the on-road flag (0: the default config has none).
        speed_levels: ``MDPVehicle.DEFAULT_TARGET_SPEEDS.size - 1``.
        normalize_reward: map ``[collision, high_speed]`` to ``[0, 1]``.
        duration: the episode's length (s).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("roundabout-v0").reward.duration
        11.0
    """

    collision_reward: float
    high_speed_reward: float
    lane_change_reward: float
    on_road_reward: float
    speed_levels: int
    normalize_reward: bool
    duration: float


@dataclass(frozen=True)
class RoundaboutParams:
    """Everything a batched roundabout world needs besides its state.

    Attributes:
        road: the lanes, roads and paths.
        vehicle: the bicycle model.
        idm: the IDM and MOBIL constants.
        control: the controllers and the ego's target speeds.
        time: frequencies.
        traffic: the reset's spawn table.
        reward: the reward and the episode's end.
        observation: the Kinematics table.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("roundabout-v0").route_length
        11
    """

    road: RoundaboutRoad
    vehicle: VehicleParams
    idm: IDMParams
    control: ControlParams
    time: TimeParams
    traffic: RoundaboutTraffic
    reward: RoundaboutReward
    observation: ObservationParams

    @property
    def num_vehicles(self) -> int:
        """Rows of the vehicle table: the ego and the IDM vehicles."""
        return self.traffic.vehicles_count + 1

    @property
    def obstacle_row(self) -> int:
        """One past the last vehicle: the roundabout has no obstacle (the merge step reads it)."""
        return self.num_vehicles

    @property
    def route_length(self) -> int:
        """The legs a route holds."""
        return self.road.route_length
