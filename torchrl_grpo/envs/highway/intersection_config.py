"""intersection-v0 on the tensor simulator: its config scope and its constants, from highway-env.

:func:`~torchrl_grpo.envs.highway.tensor_params` calls these for ``"intersection-v0"``:
the lanes, roads, links and priorities come from ``IntersectionEnv``'s own network
(:func:`~.lane_constants.road_graph`), the shortest paths from its ``shortest_path``,
the rule pass from ``RegulatedRoad``'s class constants, and the spawn table from the
literals of ``_make_vehicles``, ``_spawn_vehicle``, ``_clear_vehicles`` and
``has_arrived`` (named below).

Example:
    >>> params = intersection_params(json.dumps(IntersectionEnv.default_config(), default=str))
    >>> params.traffic.entry_lanes, params.traffic.max_vehicles
    ((0, 5, 10, 15), 23)
"""

from __future__ import annotations

import functools
import json
import math

import gymnasium as gym
import numpy as np
from highway_env.envs.intersection_env import IntersectionEnv  # noqa: F401 - the examples use it
from highway_env.road.regulation import RegulatedRoad

from torchrl_grpo.envs.highway.lane_constants import road_graph
from torchrl_grpo.envs.highway.model_constants import (
    check_numbers_and_timing,
    model_constants,
    observation_params,
)
from torchrl_grpo.envs.highway.schema import PRISTINE_CLASS_PARAMETERS
from torchrl_grpo.sim.intersection_params import (
    IntersectionParams,
    IntersectionReward,
    IntersectionRoad,
    IntersectionTraffic,
    RegulationParams,
)
from torchrl_grpo.sim.params import TimeParams

__all__ = ["INTERSECTION_SUPPORTED", "check_intersection_values", "intersection_params"]

#: Config keys of intersection-v0 the simulator reads (besides the rendering keys).
INTERSECTION_SUPPORTED = (
    "observation", "action", "simulation_frequency", "policy_frequency", "duration",
    "destination", "initial_vehicle_count", "spawn_probability", "collision_reward",
    "high_speed_reward", "arrived_reward", "reward_speed_range", "normalize_reward",
    "offroad_terminal",
)  # fmt: skip

# Literals of highway-env 1.12.1's intersection_env.py: _make_vehicles writes IDM's
# DISTANCE_WANTED, COMFORT_ACC_MAX and COMFORT_ACC_MIN process-wide, simulates 3 seconds
# before the challenger (spawned at 60 m, deviations 0.1 m and 0 m/s) and the ego (at
# 60 + 5 * normal(1) m), and removes vehicles within 20 m of the ego; _spawn_vehicle
# places a car at longitudinal + 5 + normal() m at 8 + normal() m/s and drops it within
# 15 m of another (at reset with its default probability 0.6); _clear_vehicles removes
# cars 4 lengths before an exit lane's end; has_arrived's exit_distance is 25 m.
_IDM = {"distance_wanted": 7.0, "comfort_acc_max": 6.0, "comfort_acc_min": -3.0}
_WARMUP_SECONDS = 3
_CHALLENGER = {"s": 60.0, "position": 0.1, "speed": 0.0}
_EGO = {"s": 60.0, "scale": 5.0, "loc": 1.0, "clearance": 20.0}
_SPAWN = {
    "probability": 0.6,
    "offset": 5.0,
    "speed": 8.0,
    "deviation": 1.0,
    "clearance": 15.0,
    "last_s": 80.0,
}
_LEAVE_LENGTHS = 4
_ARRIVE = 25.0
# RegulatedRoad.is_conflict_possible's defaults: horizon 3 s in steps of 0.25 s, the
# rectangles 1.5 lengths by 0.9 widths.
_CONFLICT = {"horizon": 3, "step": 0.25, "length": 1.5, "width": 0.9}


def check_intersection_values(full: dict, refuse) -> None:
    """Refuse intersection-v0 config values the simulator cannot take (``refuse(key, why)``).

    Example:
        >>> def refuse(key, why):
        ...     raise ValueError(key)
        >>> check_intersection_values(IntersectionEnv.default_config(), refuse)
    """
    numbers = (
        "collision_reward", "high_speed_reward", "arrived_reward", "simulation_frequency",
        "policy_frequency", "duration", "spawn_probability",
    )  # fmt: skip
    check_numbers_and_timing(full, numbers, refuse)
    for key in ("normalize_reward", "offroad_terminal"):
        if not isinstance(full[key], bool):
            refuse(key, "expected a bool")
    if full["normalize_reward"] and full["collision_reward"] == full["arrived_reward"]:
        refuse("collision_reward", "normalize_reward divides by arrived - collision")
    count = full["initial_vehicle_count"]
    if not isinstance(count, int) or isinstance(count, bool) or count < 2:
        refuse("initial_vehicle_count", "an integer >= 2 (the reset spawns count - 1, then one)")
    if not 0 <= full["spawn_probability"] <= 1:
        refuse("spawn_probability", "a probability in [0, 1]")
    if full["destination"] not in (None, "o1", "o2", "o3"):
        refuse("destination", "None (drawn) or one of 'o1', 'o2', 'o3'")
    speeds = full["reward_speed_range"]
    if len(speeds) != 2 or not float(speeds[1]) > float(speeds[0]):
        refuse("reward_speed_range", "two speeds, low < high")


@functools.lru_cache(maxsize=16)
def intersection_params(config_json: str) -> IntersectionParams:
    """The :class:`~torchrl_grpo.sim.intersection_params.IntersectionParams` of a full config.

    Example:
        >>> config = json.dumps(IntersectionEnv.default_config(), default=str)
        >>> intersection_params(config).num_vehicles
        24
    """
    full = json.loads(config_json)
    env = gym.make("intersection-v0", config=full, disable_env_checker=True)
    try:
        env.reset(seed=0)
        core = env.unwrapped
        network, ego = core.road.network, core.vehicle
        graph = road_graph(network)
        flat = {key: k for k, key in enumerate(graph.keys)}
        speed_limits = set(graph.speed_limit)
        if len(speed_limits) != 1 or any(len(network.graph[k[0]][k[1]]) != 1 for k in graph.keys):
            raise ValueError("the tensor simulator assumes one lane a road and one speed limit")
        if RegulatedRoad.YIELD_DURATION != 0:  # a yield then lasts until the next rule pass
            raise ValueError("the tensor simulator assumes RegulatedRoad.YIELD_DURATION = 0")
        roads = [k[:2] for k in graph.keys]
        nodes = list(dict.fromkeys(n for r in roads for n in r))
        leaving = [[roads.index((t, n)) for n in network.graph.get(t, {})] for _, t in roads]
        fan = max(len(row) for row in leaving)
        destinations = tuple(f"o{c}" for c in range(4))

        def path_roads(start: str, goal: str) -> tuple[int, ...]:
            path = network.shortest_path(start, goal)
            return tuple(roads.index((a, b)) for a, b in zip(path, path[1:], strict=False))

        paths = tuple(tuple(path_roads(t, d) for d in destinations) for _, t in roads)
        config = core.config
        frequency = float(config["simulation_frequency"])
        ego_lane = network.get_lane(("o0", "ir0", 0))
        count = int(config["initial_vehicle_count"])
        steps = math.ceil(float(config["duration"]) * float(config["policy_frequency"]))
        destination = config["destination"]
        constants = model_constants(ego)
        core.observation_type.observe()
        return IntersectionParams(
            road=IntersectionRoad(
                lanes=graph.geometry, lane_id=graph.lane_id, road=tuple(range(len(roads))),
                left=graph.left, right=graph.right, side_left=(-1,) * len(roads),
                side_right=(-1,) * len(roads), lanes_count=len(roads),
                speed_limit=speed_limits.pop(), road_from=tuple(nodes.index(f) for f, _ in roads),
                road_to=tuple(nodes.index(t) for _, t in roads),
                road_lanes=tuple((k,) for k in range(len(roads))),
                next_roads=tuple(tuple(row) + (-1,) * (fan - len(row)) for row in leaving),
                destinations=destinations, paths=paths,
                route_length=1 + max(len(p) for per in paths for p in per),
                priority=tuple(int(network.get_lane(k).priority) for k in graph.keys),
                exit=tuple("il" in f and "o" in t for f, t in roads),
            ),
            vehicle=constants["vehicle"],
            idm=constants["idm"].__class__(**{**constants["idm"].__dict__, **_IDM}),
            control=constants["control"],
            time=TimeParams(
                simulation_frequency=frequency,
                policy_frequency=float(config["policy_frequency"]),
            ),
            traffic=IntersectionTraffic(
                max_vehicles=count + steps,
                initial_vehicle_count=count,
                spawn_probability=float(config["spawn_probability"]),
                initial_spawn_probability=_SPAWN["probability"],
                entry_lanes=tuple(flat[(f"o{c}", f"ir{c}", 0)] for c in range(4)),
                spawn_offset=_SPAWN["offset"],
                spawn_speed=_SPAWN["speed"],
                position_deviation=_SPAWN["deviation"],
                speed_deviation=_SPAWN["deviation"],
                spawn_s=tuple(float(s) for s in np.linspace(0, _SPAWN["last_s"], count)[:-1]),
                spawn_clearance=_SPAWN["clearance"],
                warmup_frames=int(_WARMUP_SECONDS * frequency),
                challenger_s=_CHALLENGER["s"],
                challenger_position_deviation=_CHALLENGER["position"],
                challenger_speed_deviation=_CHALLENGER["speed"],
                ego_lane=flat[("o0", "ir0", 0)],
                ego_s=_EGO["s"],
                ego_scale=_EGO["scale"],
                ego_loc=_EGO["loc"],
                ego_speed=float(ego_lane.speed_limit),
                ego_heading=float(ego_lane.heading_at(_EGO["s"])),
                ego_destination=-1 if destination is None else destinations.index(destination),
                ego_clearance=_EGO["clearance"],
                leave_margin=_LEAVE_LENGTHS * constants["vehicle"].length,
                arrive_distance=_ARRIVE,
                others_check_collisions=all(v.check_collisions for v in core.road.vehicles),
            ),
            regulation=RegulationParams(
                every=int(1 / (1 / frequency) / RegulatedRoad.REGULATION_FREQUENCY),
                times=tuple(float(t) for t in np.arange(_CONFLICT["step"], _CONFLICT["horizon"],
                                                        _CONFLICT["step"])),
                length_scale=_CONFLICT["length"],
                width_scale=_CONFLICT["width"],
            ),  # fmt: skip
            reward=IntersectionReward(
                collision_reward=float(config["collision_reward"]),
                high_speed_reward=float(config["high_speed_reward"]),
                arrived_reward=float(config["arrived_reward"]),
                reward_speed_range=tuple(float(s) for s in config["reward_speed_range"]),
                normalize_reward=bool(config["normalize_reward"]),
                offroad_terminal=bool(config["offroad_terminal"]),
                duration=float(config["duration"]),
            ),
            observation=observation_params(core),
        )  # fmt: skip
    finally:
        env.close()
        # The reset wrote intersection-v0's IDM constants onto the classes, process-wide.
        for (cls, name), value in PRISTINE_CLASS_PARAMETERS.items():
            setattr(cls, name, value)
