"""roundabout-v0 on the tensor simulator: its config scope and its constants, read from highway-env.

:func:`~torchrl_grpo.envs.highway.tensor_params` calls these for ``"roundabout-v0"``:
the lanes, roads and links come from ``RoundaboutEnv``'s own network
(:func:`~.lane_constants.road_graph`), the shortest paths from its ``shortest_path``,
the ego's spawn from a reset env, the other vehicles' spawn table from the literals
of ``_make_vehicles`` (named below).

Example:
    >>> params = roundabout_params(json.dumps(RoundaboutEnv.default_config(), default=str))
    >>> params.road.destinations, params.traffic.spawn_lanes
    (('nxs', 'exr', 'sxr', 'nxr'), (16, 15, 15, 23))
"""

from __future__ import annotations

import functools
import json

import gymnasium as gym
from highway_env.envs.roundabout_env import RoundaboutEnv  # noqa: F401 - the examples use it
from highway_env.vehicle.controller import MDPVehicle

from torchrl_grpo.envs.highway.lane_constants import road_graph
from torchrl_grpo.envs.highway.model_constants import (
    check_numbers_and_timing,
    model_constants,
    observation_params,
)
from torchrl_grpo.sim.params import TimeParams
from torchrl_grpo.sim.roundabout_params import (
    RoundaboutParams,
    RoundaboutReward,
    RoundaboutRoad,
    RoundaboutTraffic,
)

__all__ = ["ROUNDABOUT_SUPPORTED", "check_roundabout_values", "roundabout_params"]

#: Config keys of roundabout-v0 the simulator reads (besides the rendering keys).
ROUNDABOUT_SUPPORTED = (
    "observation", "action", "simulation_frequency", "policy_frequency", "collision_reward",
    "high_speed_reward", "lane_change_reward", "right_lane_reward", "duration",
    "normalize_reward", "incoming_vehicle_destination",
)  # fmt: skip

# Literals of RoundaboutEnv._make_vehicles (highway-env 1.12.1): the IDM vehicles' lanes
# and longitudinal positions before the normal draws (the incoming car, the two on the
# ring, the entering car), the draws' scales, their speed, the routes' destinations.
_SPAWN_LANES = (("we", "sx", 1), ("we", "sx", 0), ("we", "sx", 0), ("eer", "ees", 0))
_SPAWN_S = (5.0, 20.0 * 1.0, 20.0 * -1.0, 50.0)
_DEVIATION = 2.0
_SPEED = 16.0
_DESTINATIONS = ("exr", "sxr", "nxr")
_EGO_DESTINATION = "nxs"


def check_roundabout_values(full: dict, refuse) -> None:
    """Refuse roundabout-v0 config values the simulator cannot take (``refuse(key, why)``).

    Example:
        >>> def refuse(key, why):
        ...     raise ValueError(key)
        >>> check_roundabout_values(RoundaboutEnv.default_config(), refuse)
    """
    numbers = (
        "collision_reward", "high_speed_reward", "lane_change_reward", "right_lane_reward",
        "simulation_frequency", "policy_frequency", "duration",
    )  # fmt: skip
    check_numbers_and_timing(full, numbers, refuse)
    if not isinstance(full["normalize_reward"], bool):
        refuse("normalize_reward", "expected a bool")
    if full["normalize_reward"] and full["collision_reward"] == full["high_speed_reward"]:
        refuse("collision_reward", "normalize_reward divides by high_speed - collision")
    if full["incoming_vehicle_destination"] is not None:
        refuse("incoming_vehicle_destination", "only None (a drawn destination) is simulated")


@functools.lru_cache(maxsize=16)
def roundabout_params(config_json: str) -> RoundaboutParams:
    """The :class:`~torchrl_grpo.sim.roundabout_params.RoundaboutParams` of a full config (JSON).

    Example:
        >>> roundabout_params(json.dumps(RoundaboutEnv.default_config(), default=str)).num_vehicles
        5
    """
    full = json.loads(config_json)
    env = gym.make("roundabout-v0", config=full, disable_env_checker=True)
    try:
        env.reset(seed=0)
        core = env.unwrapped
        road, ego = core.road, core.vehicle
        network = road.network
        graph = road_graph(network)
        flat = {key: k for k, key in enumerate(graph.keys)}
        if len(road.vehicles) != len(_SPAWN_LANES) + 1 or road.objects:
            raise ValueError("roundabout-v0's reset no longer builds the road the simulator models")
        speed_limits = set(graph.speed_limit)
        if len(speed_limits) != 1:
            raise ValueError("the tensor simulator assumes one speed limit on every lane")
        roads = list(dict.fromkeys(k[:2] for k in graph.keys))
        road_of = {r: i for i, r in enumerate(roads)}
        nodes = list(dict.fromkeys(n for r in roads for n in r))
        node = {n: i for i, n in enumerate(nodes)}
        width = max(len(network.graph[f][t]) for f, t in roads)
        lanes = [
            tuple(flat[(f, t, i)] for i in range(len(network.graph[f][t])))
            + (-1,) * (width - len(network.graph[f][t]))
            for f, t in roads
        ]
        fan = max(len(network.graph.get(t, {})) for _, t in roads)
        leaving = [
            tuple(road_of[(t, n)] for n in network.graph.get(t, {}))
            + (-1,) * (fan - len(network.graph.get(t, {})))
            for _, t in roads
        ]
        destinations = (_EGO_DESTINATION, *_DESTINATIONS)
        paths = []
        for _, t in roads:
            per = []
            for d in destinations:
                path = network.shortest_path(t, d) if t in network.graph else []
                per.append(tuple(road_of[(a, b)] for a, b in zip(path, path[1:], strict=False)))
            paths.append(tuple(per))
        ids = graph.lane_id
        counts = [len(network.graph[k[0]][k[1]]) for k in graph.keys]
        config = core.config
        core.observation_type.observe()
        return RoundaboutParams(
            road=RoundaboutRoad(
                lanes=graph.geometry,
                lane_id=ids,
                road=tuple(road_of[k[:2]] for k in graph.keys),
                left=graph.left,
                right=graph.right,
                side_left=tuple(k - 1 if ids[k] > 0 else -1 for k in range(len(ids))),
                side_right=tuple(k + 1 if ids[k] < counts[k] - 1 else -1 for k in range(len(ids))),
                lanes_count=len(graph.keys),
                speed_limit=speed_limits.pop(),
                road_from=tuple(node[f] for f, _ in roads),
                road_to=tuple(node[t] for _, t in roads),
                road_lanes=tuple(lanes),
                next_roads=tuple(leaving),
                destinations=destinations,
                paths=tuple(paths),
                route_length=1 + max(len(p) for per in paths for p in per),
            ),
            **model_constants(ego),
            time=TimeParams(
                simulation_frequency=float(config["simulation_frequency"]),
                policy_frequency=float(config["policy_frequency"]),
            ),
            traffic=RoundaboutTraffic(
                vehicles_count=len(road.vehicles) - 1,
                ego_lane=flat[ego.lane_index],
                ego_s=float(ego.lane.local_coordinates(ego.position)[0]),
                ego_speed=float(ego.speed),
                ego_heading=float(ego.heading),
                ego_destination=0,
                spawn_lanes=tuple(flat[k] for k in _SPAWN_LANES),
                spawn_s=_SPAWN_S,
                position_scale=_DEVIATION,
                spawn_speed=_SPEED,
                speed_scale=_DEVIATION,
                destinations=tuple(range(1, len(destinations))),
                others_check_collisions=all(v.check_collisions for v in road.vehicles),
            ),
            reward=RoundaboutReward(
                collision_reward=float(config["collision_reward"]),
                high_speed_reward=float(config["high_speed_reward"]),
                lane_change_reward=float(config["lane_change_reward"]),
                on_road_reward=float(config.get("on_road_reward", 0)),
                speed_levels=int(MDPVehicle.DEFAULT_TARGET_SPEEDS.size - 1),
                normalize_reward=bool(config["normalize_reward"]),
                duration=float(config["duration"]),
            ),
            observation=observation_params(core),
        )
    finally:
        env.close()
