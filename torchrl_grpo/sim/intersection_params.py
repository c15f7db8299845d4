"""The constants of intersection-v0: its road with priorities, its traffic, its regulation.

:class:`IntersectionParams` has the fields the shared pure functions read (``vehicle``,
``idm``, ``control``, ``time``, ``observation``, ``road`` with the routes of
:mod:`.routes`), and the intersection's own: each lane's priority and whether it is an
exit (:class:`IntersectionRoad`), the spawns (:class:`IntersectionTraffic`), the
right-of-way rules of ``RegulatedRoad`` (:class:`RegulationParams`) and the reward
(:class:`IntersectionReward`). Every value is read from highway-env by
:func:`torchrl_grpo.envs.highway.tensor_params`.

The vehicle table has a row per vehicle the episode can hold: row 0 is the ego, rows
``1..`` the IDM vehicles in ``road.vehicles`` order, packed from row 1, with ``present``
False on the free rows. Vehicles come and go during an episode (spawns, exits).

Example:
    >>> from torchrl_grpo.envs import tensor_params
    >>> params = tensor_params("intersection-v0")
    >>> params.road.lanes_count, params.num_vehicles, params.road.priority[:4]
    (20, 24, (1, 1, 0, 1))
"""

from __future__ import annotations

from dataclasses import dataclass

from torchrl_grpo.sim.params import (
    ControlParams,
    IDMParams,
    ObservationParams,
    TimeParams,
    VehicleParams,
)
from torchrl_grpo.sim.roundabout_params import RoundaboutRoad

__all__ = [
    "IntersectionParams",
    "IntersectionReward",
    "IntersectionRoad",
    "IntersectionTraffic",
    "RegulationParams",
]


@dataclass(frozen=True)
class IntersectionRoad(RoundaboutRoad):
    """The roundabout's road fields (lanes, roads, paths), with priorities and exits.

    Attributes:
        priority: each lane's ``priority`` (who yields at a conflict).
        exit: each lane runs from an inner node ``il*`` to an outer one ``o*`` (where
            vehicles arrive and leave).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> road = tensor_params("intersection-v0").road
        >>> road.destinations, sum(road.exit)
        (('o0', 'o1', 'o2', 'o3'), 4)
    """

    priority: tuple[int, ...] = ()
    exit: tuple[bool, ...] = ()


@dataclass(frozen=True)
class IntersectionTraffic:
    """``IntersectionEnv._make_vehicles``, ``_spawn_vehicle`` and ``_clear_vehicles``.

    Attributes:
        max_vehicles: the table's rows besides the ego.
        initial_vehicle_count: the reset's spawn count (the first ``count - 1`` at
            ``spawn_s``, then the challenger).
        spawn_probability: a step's chance of a spawn attempt.
        initial_spawn_probability: the reset's (``_spawn_vehicle``'s default argument).
        entry_lanes: the incoming lane of each corner (flat ids, corner order).
        spawn_offset: added to each spawn's longitudinal position (m).
        spawn_speed: the spawn speed before the speed deviation (m/s).
        position_deviation: the normal draw's scale on a spawn's position (m).
        speed_deviation: the normal draw's scale on its speed (m/s).
        spawn_s: the reset's first spawns' longitudinal positions.
        spawn_clearance: a spawn closer than this to any vehicle is dropped (m).
        warmup_frames: the frames the reset simulates before the challenger and ego.
        challenger_s: the challenger's longitudinal position.
        challenger_position_deviation: its normal draw's scale (m).
        challenger_speed_deviation: its speed's (m/s).
        ego_lane: the ego's spawn lane (flat id).
        ego_s: ``60``: its position is ``ego_s + ego_scale * normal(ego_loc)``.
        ego_scale: see ``ego_s``.
        ego_loc: see ``ego_s``.
        ego_speed: its speed (the lane's speed limit).
        ego_heading: the lane's heading at ``ego_s``.
        ego_destination: the index in ``road.destinations`` of its route's end, -1 to
            draw one of ``o1 .. o3``.
        ego_clearance: vehicles closer than this to the ego are removed at reset (m).
        leave_margin: a vehicle on an exit lane leaves when ``s >= length - margin``.
        arrive_distance: the ego has arrived when ``s >= arrive_distance`` on an exit.
        others_check_collisions: True: every vehicle checks collisions.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("intersection-v0").traffic.spawn_s[:3]
        (0.0, 8.88888888888889, 17.77777777777778)
    """

    max_vehicles: int
    initial_vehicle_count: int
    spawn_probability: float
    initial_spawn_probability: float
    entry_lanes: tuple[int, ...]
    spawn_offset: float
    spawn_speed: float
    position_deviation: float
    speed_deviation: float
    spawn_s: tuple[float, ...]
    spawn_clearance: float
    warmup_frames: int
    challenger_s: float
    challenger_position_deviation: float
    challenger_speed_deviation: float
    ego_lane: int
    ego_s: float
    ego_scale: float
    ego_loc: float
    ego_speed: float
    ego_heading: float
    ego_destination: int
    ego_clearance: float
    leave_margin: float
    arrive_distance: float
    others_check_collisions: bool


@dataclass(frozen=True)
class RegulationParams:
    """``RegulatedRoad.enforce_road_rules``: every ``every`` road frames, conflicts yield.

    Attributes:
        every: the road frames between two rule passes (``int(1 / dt / frequency)``).
        times: the prediction times of ``is_conflict_possible`` (s).
        length_scale: the predicted rectangles' length, in vehicle lengths.
        width_scale: their width, in vehicle widths.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> reg = tensor_params("intersection-v0").regulation
        >>> reg.every, len(reg.times)
        (7, 11)
    """

    every: int
    times: tuple[float, ...]
    length_scale: float
    width_scale: float


@dataclass(frozen=True)
class IntersectionReward:
    """``IntersectionEnv._agent_reward``, ``_is_terminated`` and ``_is_truncated``.

    Attributes:
        collision_reward: weight of the crash flag.
        high_speed_reward: weight of the speed mapped from ``reward_speed_range``.
        arrived_reward: the reward once arrived (it replaces the sum).
        reward_speed_range: the speeds mapped to ``[0, 1]``.
        normalize_reward: map ``[collision, arrived]`` to ``[0, 1]``.
        offroad_terminal: leaving the lane ends the episode.
        duration: the episode's length (s).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("intersection-v0").reward.duration
        13.0
    """

    collision_reward: float
    high_speed_reward: float
    arrived_reward: float
    reward_speed_range: tuple[float, float]
    normalize_reward: bool
    offroad_terminal: bool
    duration: float


@dataclass(frozen=True)
class IntersectionParams:
    """Everything a batched intersection world needs besides its state.

    Attributes:
        road: the lanes, roads, paths, priorities and exits.
        vehicle: the bicycle model.
        idm: the IDM constants (intersection-v0's own jam distance and comfort range).
        control: the controllers and the ego's target speeds.
        time: frequencies.
        traffic: spawns and exits.
        regulation: the right-of-way rules.
        reward: the reward and the episode's end.
        observation: the Kinematics table.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> tensor_params("intersection-v0").control.target_speeds
        (0.0, 4.5, 9.0)
    """

    road: IntersectionRoad
    vehicle: VehicleParams
    idm: IDMParams
    control: ControlParams
    time: TimeParams
    traffic: IntersectionTraffic
    regulation: RegulationParams
    reward: IntersectionReward
    observation: ObservationParams

    @property
    def num_vehicles(self) -> int:
        """Rows of the vehicle table: the ego and ``traffic.max_vehicles``."""
        return self.traffic.max_vehicles + 1

    @property
    def obstacle_row(self) -> int:
        """One past the last row: no obstacle (the merge step reads it)."""
        return self.num_vehicles

    @property
    def route_length(self) -> int:
        """The legs a route holds."""
        return self.road.route_length
