"""The constants of a batched highway world: road, vehicle models, time, traffic, reward, view.

Every field is a plain Python number, so the step functions that read them stay pure
functions of tensors and ``torch.compile`` folds them as constants. Nothing here has a
default: the values are read once from highway-env's classes and config by the env
package (:func:`torchrl_grpo.envs.highway.tensor_params`), so that the simulator
never retypes a constant of the model it re-implements.

Example:
    >>> from torchrl_grpo.envs import tensor_params
    >>> params = tensor_params("highway-fast-v0")
    >>> params.road.lanes_count, params.time.frames, params.traffic.vehicles_count
    (3, 5, 20)
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "ControlParams",
    "HighwayParams",
    "IDMParams",
    "ObservationParams",
    "RewardParams",
    "RoadParams",
    "TimeParams",
    "TrafficParams",
    "VehicleParams",
]


@dataclass(frozen=True)
class RoadParams:
    """Straight parallel lanes along x: lane ``i`` runs from ``(0, i * width)``.

    Attributes:
        lanes_count: number of lanes; lane 0 (y = 0) is the leftmost.
        lane_width: width of every lane (m).
        lane_length: length of every lane (m).
        speed_limit: every lane's speed limit (m/s), which caps IDM target speeds.
        margin_length: ``AbstractLane.VEHICLE_LENGTH``, the longitudinal margin of
            ``on_lane`` and ``is_reachable_from`` (m).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.road.lanes_count, params.road.lane_width
        (3, 4.0)
    """

    lanes_count: int
    lane_width: float
    lane_length: float
    speed_limit: float
    margin_length: float


@dataclass(frozen=True)
class VehicleParams:
    """The kinematic bicycle shared by every vehicle.

    Attributes:
        length: body length (m), also the bicycle's wheelbase.
        width: body width (m).
        max_speed: above it, acceleration is clipped towards it (m/s).
        min_speed: below it, acceleration is clipped towards it (m/s).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.vehicle.length, params.vehicle.max_speed
        (5.0, 40.0)
    """

    length: float
    width: float
    max_speed: float
    min_speed: float


@dataclass(frozen=True)
class IDMParams:
    """``IDMVehicle``'s longitudinal (IDM) and lateral (MOBIL) constants.

    Attributes:
        acc_max: clip of the commanded acceleration (m/s^2).
        comfort_acc_max: IDM's desired acceleration (m/s^2).
        comfort_acc_min: IDM's desired deceleration, negative (m/s^2).
        distance_wanted: jam distance (m).
        time_wanted: time gap (s).
        delta_range: the range of each vehicle's velocity exponent, drawn at reset.
        politeness: MOBIL's weight of the followers' accelerations.
        lane_change_min_acc_gain: MOBIL's acceleration gain threshold (m/s^2).
        lane_change_max_braking_imposed: MOBIL's safety threshold (m/s^2).
        lane_change_delay: seconds between two lane-change decisions.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.idm.delta_range, params.idm.lane_change_delay
        ((3.5, 4.5), 1.0)
    """

    acc_max: float
    comfort_acc_max: float
    comfort_acc_min: float
    distance_wanted: float
    time_wanted: float
    delta_range: tuple[float, float]
    politeness: float
    lane_change_min_acc_gain: float
    lane_change_max_braking_imposed: float
    lane_change_delay: float


@dataclass(frozen=True)
class ControlParams:
    """``ControlledVehicle``'s speed and steering controllers, and the ego's target speeds.

    Attributes:
        kp_a: speed-control gain (1/s).
        kp_heading: heading-control gain (1/s).
        kp_lateral: lateral-position gain (1/s).
        tau_pursuit: look-ahead time of the lane heading (s).
        max_steering_angle: steering clip (rad).
        target_speeds: the ego's discrete target speeds (``DiscreteMetaAction``).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.control.kp_heading, params.control.target_speeds
        (5.0, (20.0, 25.0, 30.0))
    """

    kp_a: float
    kp_heading: float
    kp_lateral: float
    tau_pursuit: float
    max_steering_angle: float
    target_speeds: tuple[float, ...]


@dataclass(frozen=True)
class TimeParams:
    """Simulation and policy frequencies.

    Attributes:
        simulation_frequency: substeps per second.
        policy_frequency: env steps (decisions) per second.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.time.frames, params.time.dt
        (5, 0.2)
    """

    simulation_frequency: float
    policy_frequency: float

    @property
    def dt(self) -> float:
        """Seconds per substep, ``1 / simulation_frequency`` as highway-env computes it."""
        return 1 / self.simulation_frequency

    @property
    def frames(self) -> int:
        """Substeps per env step: ``int(simulation_frequency // policy_frequency)``."""
        return int(self.simulation_frequency // self.policy_frequency)

    @property
    def step_time(self) -> float:
        """What ``time`` gains per env step: ``1 / policy_frequency``."""
        return 1 / self.policy_frequency


@dataclass(frozen=True)
class TrafficParams:
    """How ``reset`` draws a world (``HighwayEnv._create_vehicles``, ``create_random``).

    Attributes:
        vehicles_count: IDM vehicles besides the ego.
        vehicles_density: the others' spacing is ``1 / vehicles_density``.
        ego_spacing: the ego's spacing.
        initial_lane_id: the ego's lane, or ``None`` for a uniform draw.
        ego_speed: the ego's initial speed (m/s).
        speed_low: lower bound of the others' initial speed, a fraction of the speed limit.
        speed_high: upper bound, likewise.
        spacing_base: ``default_spacing = spacing_base + spacing_per_speed * speed`` (m).
        spacing_per_speed: see ``spacing_base`` (s).
        spacing_decay: ``offset *= exp(-spacing_decay * lanes_count)``.
        first_offsets: the rearmost vehicle starts at ``first_offsets * offset``.
        jitter: each offset is scaled by ``uniform(jitter[0], jitter[1])``.
        others_check_collisions: whether other vehicles check collisions among
            themselves (False in highway-fast-v0: only pairs with the ego are checked).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.traffic.vehicles_count, params.traffic.others_check_collisions
        (20, False)
    """

    vehicles_count: int
    vehicles_density: float
    ego_spacing: float
    initial_lane_id: int | None
    ego_speed: float
    speed_low: float
    speed_high: float
    spacing_base: float
    spacing_per_speed: float
    spacing_decay: float
    first_offsets: float
    jitter: tuple[float, float]
    others_check_collisions: bool


@dataclass(frozen=True)
class RewardParams:
    """``HighwayEnv._reward`` and the episode's end.

    Attributes:
        collision_reward: weight of the crash flag.
        right_lane_reward: weight of the (target) lane index, scaled to [0, 1].
        high_speed_reward: weight of the scaled forward speed.
        on_road_reward: weight of the on-road flag (0 unless configured).
        reward_speed_range: forward speeds mapped to [0, 1].
        normalize_reward: map the sum to [0, 1] by the collision and best weights.
        offroad_terminal: leaving the road ends the episode.
        duration: the episode is truncated when ``time >= duration`` (s).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.reward.duration, params.reward.reward_speed_range
        (30.0, (20.0, 30.0))
    """

    collision_reward: float
    right_lane_reward: float
    high_speed_reward: float
    on_road_reward: float
    reward_speed_range: tuple[float, float]
    normalize_reward: bool
    offroad_terminal: bool
    duration: float


@dataclass(frozen=True)
class ObservationParams:
    """``KinematicObservation`` with ``order="sorted"``.

    Attributes:
        vehicles_count: rows of the table, the ego's included.
        features: columns, among presence, x, y, vx, vy, heading, cos_h, sin_h, cos_d, sin_d.
        normalize: map x, y, vx and vy to [-1, 1] by ``features_range``.
        absolute: other vehicles in world coordinates, not relative to the ego.
        clip: clip normalised features to [-1, 1].
        see_behind: include vehicles more than two lengths behind the ego.
        perception_distance: only vehicles closer than this are seen (m).
        features_range: ``((name, (low, high)), ...)`` for x, y, vx, vy.
        observe_intentions: show the other vehicles' ``cos_d, sin_d`` (the direction
            to their route's end), not zeros.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> params.observation.vehicles_count, params.observation.features
        (5, ('presence', 'x', 'y', 'vx', 'vy'))
    """

    vehicles_count: int
    features: tuple[str, ...]
    normalize: bool
    absolute: bool
    clip: bool
    see_behind: bool
    perception_distance: float
    features_range: tuple[tuple[str, tuple[float, float]], ...]
    observe_intentions: bool = False


@dataclass(frozen=True)
class HighwayParams:
    """Everything a batched highway world needs besides its state.

    Attributes:
        road: the lanes.
        vehicle: the bicycle model.
        idm: the other vehicles' driver model.
        control: the controllers and the ego's target speeds.
        time: frequencies.
        traffic: how worlds are drawn.
        reward: the reward and the episode's end.
        observation: the Kinematics table.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-v0")
        >>> params.num_vehicles, params.time.frames, params.traffic.others_check_collisions
        (51, 15, True)
    """

    road: RoadParams
    vehicle: VehicleParams
    idm: IDMParams
    control: ControlParams
    time: TimeParams
    traffic: TrafficParams
    reward: RewardParams
    observation: ObservationParams

    @property
    def num_vehicles(self) -> int:
        """Rows of the vehicle table: the ego, then ``traffic.vehicles_count`` others."""
        return self.traffic.vehicles_count + 1
