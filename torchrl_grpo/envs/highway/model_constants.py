"""The vehicle, IDM and controller constants every tensor scenario reads from highway-env.

IDM's constants come from their pristine values (intersection-v0 overwrites some of
them process-wide, see :data:`~.schema.PRISTINE_CLASS_PARAMETERS`); the target speeds
come from the scenario's own ego.

Example:
    >>> import gymnasium as gym
    >>> env = gym.make("merge-v0")
    >>> _ = env.reset(seed=0)
    >>> model_constants(env.unwrapped.vehicle)["control"].target_speeds
    (20.0, 25.0, 30.0)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from torchrl_grpo.envs.highway import schema
from torchrl_grpo.sim.params import ControlParams, IDMParams, ObservationParams, VehicleParams

__all__ = ["check_numbers_and_timing", "model_constants", "observation_params"]


def observation_params(core) -> ObservationParams:
    """The Kinematics observation's settings of the reset env ``core`` (unwrapped).

    Example:
        >>> import gymnasium as gym
        >>> env = gym.make("highway-fast-v0")
        >>> _ = env.reset(seed=0)
        >>> observation_params(env.unwrapped).vehicles_count
        5
    """
    obs = core.observation_type
    return ObservationParams(
        vehicles_count=int(obs.vehicles_count),
        features=tuple(obs.features),
        normalize=bool(obs.normalize),
        absolute=bool(obs.absolute),
        clip=bool(obs.clip),
        see_behind=bool(obs.see_behind),
        perception_distance=float(core.PERCEPTION_DISTANCE),
        features_range=tuple(
            (k, (float(r[0]), float(r[1]))) for k, r in (obs.features_range or {}).items()
        ),
        observe_intentions=bool(obs.observe_intentions),
    )


def model_constants(ego) -> dict:
    """``{"vehicle", "idm", "control"}`` params, from the classes and the ego's target speeds.

    Example:
        >>> import gymnasium as gym
        >>> env = gym.make("highway-fast-v0")
        >>> _ = env.reset(seed=0)
        >>> model_constants(env.unwrapped.vehicle)["idm"].lane_change_delay
        1.0
    """
    pristine = {name: v for (_, name), v in schema.PRISTINE_CLASS_PARAMETERS.items()}

    def idm(name: str) -> float:
        return float(pristine.get(name, getattr(IDMVehicle, name)))

    return {
        "vehicle": VehicleParams(
            length=float(Vehicle.LENGTH),
            width=float(Vehicle.WIDTH),
            max_speed=float(Vehicle.MAX_SPEED),
            min_speed=float(Vehicle.MIN_SPEED),
        ),
        "idm": IDMParams(
            acc_max=idm("ACC_MAX"),
            comfort_acc_max=idm("COMFORT_ACC_MAX"),
            comfort_acc_min=idm("COMFORT_ACC_MIN"),
            distance_wanted=idm("DISTANCE_WANTED"),
            time_wanted=idm("TIME_WANTED"),
            delta_range=tuple(float(d) for d in IDMVehicle.DELTA_RANGE),
            politeness=idm("POLITENESS"),
            lane_change_min_acc_gain=idm("LANE_CHANGE_MIN_ACC_GAIN"),
            lane_change_max_braking_imposed=idm("LANE_CHANGE_MAX_BRAKING_IMPOSED"),
            lane_change_delay=idm("LANE_CHANGE_DELAY"),
        ),
        "control": ControlParams(
            kp_a=float(ControlledVehicle.KP_A),
            kp_heading=float(ControlledVehicle.KP_HEADING),
            kp_lateral=float(ControlledVehicle.KP_LATERAL),
            tau_pursuit=float(ControlledVehicle.TAU_PURSUIT),
            max_steering_angle=float(ControlledVehicle.MAX_STEERING_ANGLE),
            target_speeds=tuple(float(s) for s in ego.target_speeds),
        ),
    }


def check_numbers_and_timing(
    full: dict, numbers: Sequence[str], refuse: Callable[[str, str], None]
) -> None:
    """Refuse ``numbers`` that are not finite, a non-positive timing, or no substep a step.

    ``numbers`` must include the timing keys ``simulation_frequency`` and
    ``policy_frequency`` (and ``duration`` where the scenario has one), which must also be
    positive; ``refuse(key, why)`` raises.

    Example:
        >>> def refuse(key, why):
        ...     raise ValueError(f"{key}: {why}")
        >>> full = {"simulation_frequency": 15, "policy_frequency": 0}
        >>> try:
        ...     check_numbers_and_timing(full, list(full), refuse)
        ... except ValueError as err:
        ...     print(err)
        policy_frequency: expected a positive number
    """
    for key in numbers:
        value = full[key]
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or not math.isfinite(value):
            refuse(key, "expected a finite number")
    for key in ("simulation_frequency", "policy_frequency", "duration"):
        if key in numbers and full[key] <= 0:
            refuse(key, "expected a positive number")
    if full["simulation_frequency"] // full["policy_frequency"] < 1:
        refuse("simulation_frequency", "at least one substep per policy step")
