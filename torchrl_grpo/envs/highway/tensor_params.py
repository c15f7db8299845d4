"""What the batched simulator covers of highway-env, and its constants read from highway-env.

:func:`tensor_params` checks a scenario and config against what
:mod:`torchrl_grpo.sim` simulates and returns the :class:`~torchrl_grpo.sim.HighwayParams`
read from a live highway-env env of that config: lane geometry and speed limit from
its road, vehicle and controller constants from its classes (the IDM constants that
intersection-v0 overwrites process-wide from their pristine values), the target
speeds from its ego, the observation's ranges from its observation type. The few
numbers that highway-env writes as literals inside ``_create_vehicles`` and
``Vehicle.create_random`` are named here, with where they come from.

Example:
    >>> params = tensor_params("highway-v0", {"lanes_count": 3, "vehicles_count": 10})
    >>> params.road.lanes_count, params.num_vehicles, params.time.frames
    (3, 11, 15)
    >>> try:
    ...     tensor_params("highway-fast-v0", {"manual_control": True})
    ... except ValueError as err:
    ...     print(str(err)[:60])
    highway-fast-v0 config: manual_control=True is not supported
"""

from __future__ import annotations

import copy
import difflib
import functools
import json
import math
from typing import Any

import gymnasium as gym
import highway_env  # noqa: F401 - registers the scenarios
from highway_env.road.lane import AbstractLane

from torchrl_grpo.envs.highway.intersection_config import (
    INTERSECTION_SUPPORTED,
    check_intersection_values,
    intersection_params,
)
from torchrl_grpo.envs.highway.merge_config import MERGE_SUPPORTED, check_merge_values, merge_params
from torchrl_grpo.envs.highway.model_constants import model_constants, observation_params
from torchrl_grpo.envs.highway.roundabout_config import (
    ROUNDABOUT_SUPPORTED,
    check_roundabout_values,
    roundabout_params,
)
from torchrl_grpo.sim.merge_params import MergeParams
from torchrl_grpo.sim.observation import FEATURES
from torchrl_grpo.sim.params import (
    HighwayParams,
    RewardParams,
    RoadParams,
    TimeParams,
    TrafficParams,
)
from torchrl_grpo.sim.roundabout_params import RoundaboutParams

__all__ = ["TENSOR_SCENARIOS", "check_tensor_config", "tensor_params"]

#: The scenarios the batched simulator covers.
TENSOR_SCENARIOS = ("highway-v0", "highway-fast-v0", "merge-v0", "roundabout-v0", "intersection-v0")

# Config keys the simulator reads, and keys that only change rendering
# (show_trajectories is not among them: it makes highway-env keep a per-vehicle history,
# which the tensor state does not carry).
_SUPPORTED = (
    "observation", "action", "lanes_count", "vehicles_count", "vehicles_density",
    "ego_spacing", "initial_lane_id", "duration", "simulation_frequency", "policy_frequency",
    "collision_reward", "right_lane_reward", "high_speed_reward", "lane_change_reward",
    "reward_speed_range", "normalize_reward", "offroad_terminal",
)  # fmt: skip
_RENDERING = (
    "screen_width", "screen_height", "centering_position", "scaling",
    "render_agent", "offscreen_rendering", "real_time_rendering",
    # One straight road segment has no connected lanes: the flag changes nothing.
    "neighbour_vehicles_connected_lanes",
)  # fmt: skip
_OBSERVATION = (
    "type", "vehicles_count", "features", "normalize", "absolute", "clip", "see_behind",
    "observe_intentions",
)  # fmt: skip
_ACTION = ("type", "target_speeds")

# Literals of highway-env 1.12.1's reset code (no class holds them):
# Vehicle.create_random: speed ~ uniform(0.7, 0.8) * speed_limit; default_spacing =
# 12 + 1.0 * speed; offset = spacing * default_spacing * exp(-5 / 40 * lanes); the
# rearmost vehicle at 3 * offset; each offset scaled by uniform(0.9, 1.1).
_CREATE_RANDOM = {
    "speed_low": 0.7, "speed_high": 0.8, "spacing_base": 12.0, "spacing_per_speed": 1.0,
    "spacing_decay": 5 / 40, "first_offsets": 3.0, "jitter": (0.9, 1.1),
}  # fmt: skip


def check_tensor_config(scenario: str, config: dict | None = None) -> dict:
    """The scenario's full config with ``config`` applied; a ``ValueError`` for what is not covered.

    Args:
        scenario: a highway-env scenario name.
        config: overrides, applied as highway-env's ``configure`` applies them (a
            top-level update: an ``observation`` dict replaces the default one).

    Returns:
        The full config.

    Raises:
        ValueError: the scenario, a key or a value is outside the simulator's scope;
            the message names it and lists what is supported.

    Example:
        >>> check_tensor_config("highway-fast-v0")["lanes_count"]
        3
        >>> try:
        ...     check_tensor_config("racetrack-v0")
        ... except ValueError as err:
        ...     print(str(err)[:62])
        the tensor simulator covers ('highway-v0', 'highway-fast-v0',
    """
    if scenario not in TENSOR_SCENARIOS:
        raise ValueError(
            f"the tensor simulator covers {TENSOR_SCENARIOS}, not {scenario!r}; "
            "use HighwayEnv (highway-env itself) for other scenarios"
        )
    module_name, class_name = gym.spec(scenario).entry_point.split(":")
    env_class = getattr(__import__(module_name, fromlist=[class_name]), class_name)
    defaults = env_class.default_config()
    full = copy.deepcopy(defaults)
    full.update(copy.deepcopy(dict(config or {})))

    supported, check_values = {
        "merge-v0": (MERGE_SUPPORTED, check_merge_values),
        "roundabout-v0": (ROUNDABOUT_SUPPORTED, check_roundabout_values),
        "intersection-v0": (INTERSECTION_SUPPORTED, check_intersection_values),
    }.get(scenario, (_SUPPORTED, _check_values))

    def refuse(key: str, why: str) -> None:
        raise ValueError(
            f"{scenario} config: {key}={_lookup(full, key)!r} is not supported by the "
            f"tensor simulator ({why}). Supported keys: {', '.join(supported)}; observation "
            f"options {_OBSERVATION} with features among {FEATURES} and order 'sorted'; "
            f"action options {_ACTION}"
        )

    for key in sorted(set(full) - set(supported) - set(_RENDERING)):
        if key not in defaults:
            close = difflib.get_close_matches(key, list(defaults), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ValueError(f"unknown config key {key!r} for {scenario}{hint}")
        if full[key] != defaults[key]:
            refuse(key, f"only its default {defaults[key]!r} is simulated")
    # highway-env uses a configured features_range as given and fixes a missing one at the
    # first observation: the simulator reads those fixed ranges on highway and merge roads,
    # while roundabout-v0 and intersection-v0 must keep the ones their defaults give.
    ranged = scenario in ("roundabout-v0", "intersection-v0") or (
        "features_range" in full["observation"]
    )
    _check_observation(full, refuse, ranged=ranged)
    _check_action(full, refuse, defaults["action"])
    check_values(full, refuse)
    return full


def _lookup(config: dict, key: str) -> Any:
    value: Any = config
    for part in key.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def _check_observation(full: dict, refuse, ranged: bool = False) -> None:
    obs = full["observation"]
    if not isinstance(obs, dict) or obs.get("type") != "Kinematics":
        refuse("observation.type", "only the Kinematics observation is simulated")
    if ranged:
        ranges = obs.get("features_range")
        ok = isinstance(ranges, dict) and all(
            len(r) == 2 and math.isfinite(float(r[0])) and float(r[1]) > float(r[0])
            for r in ranges.values()
        )
        if not ok:
            refuse("observation.features_range", "a dict of [low, high] ranges, low < high")
    for key in obs:
        if ranged and key == "features_range":
            continue
        # intersection-v0 names flatten at its Kinematics default.
        default = key == "flatten" and obs[key] is False
        if (
            key not in _OBSERVATION
            and not (key == "order" and obs[key] == "sorted")
            and not default
        ):
            why = (
                "'shuffled' draws from numpy's generator every step"
                if key == "order"
                else "not among the simulated options"
            )
            refuse(f"observation.{key}", why)
    features = obs.get("features", ["presence", "x", "y", "vx", "vy"])
    if not features or any(f not in FEATURES for f in features):
        refuse("observation.features", f"features must be among {FEATURES}")
    count = obs.get("vehicles_count", 5)
    if not isinstance(count, int) or count < 2:
        refuse(
            "observation.vehicles_count",
            "at least 2 rows (highway-env's table with 1 row varies in size)",
        )


def _check_action(full: dict, refuse, default: dict) -> None:
    action = full["action"]
    if not isinstance(action, dict) or action.get("type") != "DiscreteMetaAction":
        refuse("action.type", "only DiscreteMetaAction is simulated")
    for key in action:
        # intersection-v0's longitudinal-only actions are simulated as it sets them.
        fixed = key in ("longitudinal", "lateral") and action[key] == default.get(key)
        if key not in _ACTION and not fixed:
            refuse(f"action.{key}", "not among the simulated options")
    speeds = action.get("target_speeds")
    if speeds is not None:
        values = [float(s) for s in speeds]
        if len(values) < 2 or any(b <= a for a, b in zip(values, values[1:], strict=False)):
            refuse("action.target_speeds", "at least two increasing speeds")


def _check_values(full: dict, refuse) -> None:
    def number(key: str, low: float | None = None, integer: bool = False) -> None:
        value = full[key]
        ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if ok and integer:
            ok = float(value).is_integer()
        if not ok or (low is not None and value < low):
            refuse(key, f"expected a finite {'integer' if integer else 'number'}"
                   + (f" >= {low}" if low is not None else ""))  # fmt: skip

    number("lanes_count", 1, integer=True)
    number("vehicles_count", 1, integer=True)
    for key in (
        "vehicles_density",
        "ego_spacing",
        "duration",
        "simulation_frequency",
        "policy_frequency",
    ):
        number(key, 1e-9)
    for key in ("collision_reward", "right_lane_reward", "high_speed_reward", "lane_change_reward"):
        number(key)
    if full["simulation_frequency"] // full["policy_frequency"] < 1:
        refuse("simulation_frequency", "at least one substep per policy step")
    lane = full["initial_lane_id"]
    if lane is not None and (not isinstance(lane, int) or not 0 <= lane < full["lanes_count"]):
        refuse("initial_lane_id", "None or a lane of the road")
    rng = full["reward_speed_range"]
    if len(rng) != 2 or not float(rng[1]) > float(rng[0]):
        refuse("reward_speed_range", "two speeds, low < high")
    for key in ("normalize_reward", "offroad_terminal"):
        if not isinstance(full[key], bool):
            refuse(key, "expected a bool")
    if full["normalize_reward"] and (
        full["high_speed_reward"] + full["right_lane_reward"] == full["collision_reward"]
    ):
        refuse(
            "collision_reward", "normalize_reward divides by high_speed + right_lane - collision"
        )


def tensor_params(
    scenario: str = "highway-fast-v0", config: dict | None = None
) -> HighwayParams | MergeParams | RoundaboutParams:
    """The simulator's constants for a scenario and config (checked by :func:`check_tensor_config`).

    Args:
        scenario: one of :data:`TENSOR_SCENARIOS`.
        config: overrides of the scenario's default config.

    Returns:
        The :class:`~torchrl_grpo.sim.HighwayParams` (a
        :class:`~torchrl_grpo.sim.merge_params.MergeParams` for ``"merge-v0"``, a
        :class:`~torchrl_grpo.sim.roundabout_params.RoundaboutParams` for ``"roundabout-v0"``).

    Raises:
        ValueError: see :func:`check_tensor_config`.

    Example:
        >>> tensor_params("highway-fast-v0").control.target_speeds
        (20.0, 25.0, 30.0)
    """
    full = check_tensor_config(scenario, config)
    if scenario == "merge-v0":
        return merge_params(json.dumps(full, sort_keys=True, default=_jsonable))
    if scenario == "roundabout-v0":
        return roundabout_params(json.dumps(full, sort_keys=True, default=_jsonable))
    if scenario == "intersection-v0":
        return intersection_params(json.dumps(full, sort_keys=True, default=_jsonable))
    return _params(scenario, json.dumps(full, sort_keys=True, default=_jsonable))


def _jsonable(value: Any) -> Any:
    return value.tolist() if hasattr(value, "tolist") else str(value)


@functools.lru_cache(maxsize=64)
def _params(scenario: str, config_json: str) -> HighwayParams:
    full = json.loads(config_json)
    env = gym.make(scenario, config=full, disable_env_checker=True)
    try:
        env.reset(seed=0)
        core = env.unwrapped
        road, ego = core.road, core.vehicle
        lane = road.network.get_lane(("0", "1", 0))
        others = [v for v in road.vehicles if v is not ego]
        config = core.config
        return HighwayParams(
            road=RoadParams(
                lanes_count=len(road.network.graph["0"]["1"]),
                lane_width=float(lane.width),
                lane_length=float(lane.length),
                speed_limit=float(lane.speed_limit),
                margin_length=float(AbstractLane.VEHICLE_LENGTH),
            ),
            **model_constants(ego),
            time=TimeParams(
                simulation_frequency=float(config["simulation_frequency"]),
                policy_frequency=float(config["policy_frequency"]),
            ),
            traffic=TrafficParams(
                vehicles_count=int(config["vehicles_count"]),
                vehicles_density=float(config["vehicles_density"]),
                ego_spacing=float(config["ego_spacing"]),
                initial_lane_id=config["initial_lane_id"],
                ego_speed=float(ego.speed),
                others_check_collisions=bool(others[0].check_collisions) if others else True,
                **_CREATE_RANDOM,
            ),
            reward=RewardParams(
                collision_reward=float(config["collision_reward"]),
                right_lane_reward=float(config["right_lane_reward"]),
                high_speed_reward=float(config["high_speed_reward"]),
                on_road_reward=float(config.get("on_road_reward", 0)),
                reward_speed_range=tuple(float(s) for s in config["reward_speed_range"]),
                normalize_reward=bool(config["normalize_reward"]),
                offroad_terminal=bool(config["offroad_terminal"]),
                duration=float(config["duration"]),
            ),
            observation=observation_params(core),
        )
    finally:
        env.close()
