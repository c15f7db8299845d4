"""merge-v0 on the tensor simulator: its config scope and its constants, read from highway-env.

:func:`~torchrl_grpo.envs.highway.tensor_params` calls these for ``"merge-v0"``: the
road's lanes and links come from ``MergeEnv``'s own network
(:func:`~.lane_constants.road_graph`), the spawn table from its reset (the lanes and
positions of a reset env; the literal offsets of ``_make_vehicles`` are named
below), the observation's ``features_range`` from the first observation of a reset
(a configured one as given; without one highway-env fixes it there, from the ego's road,
which is always ``(a, b)``).

Example:
    >>> params = merge_params(json.dumps(MergeEnv.default_config(), default=str))
    >>> params.reward.terminal_x, params.traffic.spawns[0], params.road.next_lane[8]
    (370.0, (90.0, 29.0), 4)
"""

from __future__ import annotations

import functools
import json

import gymnasium as gym
from highway_env.envs.merge_env import MergeEnv  # noqa: F401 - the examples use it
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.objects import Obstacle

from torchrl_grpo.envs.highway.lane_constants import road_graph
from torchrl_grpo.envs.highway.model_constants import (
    check_numbers_and_timing,
    model_constants,
    observation_params,
)
from torchrl_grpo.sim.merge_params import MergeParams, MergeReward, MergeRoad, MergeTraffic
from torchrl_grpo.sim.params import TimeParams

__all__ = ["MERGE_SUPPORTED", "check_merge_values", "merge_params"]

#: Config keys of merge-v0 the simulator reads (besides the rendering keys).
MERGE_SUPPORTED = (
    "observation", "action", "simulation_frequency", "policy_frequency", "collision_reward",
    "right_lane_reward", "high_speed_reward", "reward_speed_range", "merging_speed_reward",
    "lane_change_reward",
)  # fmt: skip

# Literals of MergeEnv._make_vehicles (highway-env 1.12.1): the highway cars' (s, speed)
# before jitter, the jitter bounds, the ego's s, the merging car's s and target speed.
_SPAWNS = ((90.0, 29.0), (70.0, 31.0), (5.0, 31.5))
_POSITION_JITTER, _SPEED_JITTER = (-5.0, 5.0), (-1.0, 1.0)
# MergeEnv._is_terminated: x > 370.
_TERMINAL_X = 370.0


def check_merge_values(full: dict, refuse) -> None:
    """Refuse merge-v0 config values the simulator cannot take (``refuse(key, why)``).

    Example:
        >>> def refuse(key, why):
        ...     raise ValueError(key)
        >>> check_merge_values(MergeEnv.default_config(), refuse)
    """
    numbers = (
        "collision_reward", "right_lane_reward", "high_speed_reward", "merging_speed_reward",
        "lane_change_reward", "simulation_frequency", "policy_frequency",
    )  # fmt: skip
    check_numbers_and_timing(full, numbers, refuse)
    rng = full["reward_speed_range"]
    if len(rng) != 2 or not float(rng[1]) > float(rng[0]):
        refuse("reward_speed_range", "two speeds, low < high")
    low = full["collision_reward"] + full["merging_speed_reward"]
    if low == full["high_speed_reward"] + full["right_lane_reward"]:
        refuse("collision_reward", "the reward's lmap divides by its range, here 0")


@functools.lru_cache(maxsize=16)
def merge_params(config_json: str) -> MergeParams:
    """The :class:`~torchrl_grpo.sim.merge_params.MergeParams` of a full merge-v0 config (JSON).

    Example:
        >>> merge_params(json.dumps(MergeEnv.default_config(), default=str)).road.lanes_count
        9
    """
    full = json.loads(config_json)
    env = gym.make("merge-v0", config=full, disable_env_checker=True)
    try:
        env.reset(seed=0)
        core = env.unwrapped
        road, ego = core.road, core.vehicle
        graph = road_graph(road.network)
        flat = {key: k for k, key in enumerate(graph.keys)}
        (obstacle,) = road.objects
        if type(obstacle) is not Obstacle or len(road.vehicles) != len(_SPAWNS) + 2:
            raise ValueError("merge-v0's reset no longer builds the road the simulator models")
        merging = road.vehicles[-1]
        speed_limits = set(graph.speed_limit)
        if len(speed_limits) != 1:
            raise ValueError("the tensor simulator assumes one speed limit on every lane")
        ids, roads = graph.lane_id, [graph.keys.index(k[:2] + (0,)) for k in graph.keys]
        counts = [sum(1 for k in graph.keys if k[:2] == key[:2]) for key in graph.keys]
        config = core.config
        core.observation_type.observe()  # fixes features_range, as the first observation does
        return MergeParams(
            road=MergeRoad(
                lanes=graph.geometry,
                lane_id=ids,
                road=tuple(roads),
                left=graph.left,
                right=graph.right,
                side_left=tuple(k - 1 if ids[k] > 0 else -1 for k in range(len(ids))),
                side_right=tuple(k + 1 if ids[k] < counts[k] - 1 else -1 for k in range(len(ids))),
                next_lane=graph.next_lane,
                lanes_count=len(graph.keys),
                speed_limit=speed_limits.pop(),
            ),
            **model_constants(ego),
            time=TimeParams(
                simulation_frequency=float(config["simulation_frequency"]),
                policy_frequency=float(config["policy_frequency"]),
            ),
            traffic=MergeTraffic(
                vehicles_count=len(road.vehicles) - 1,
                ego_lane=flat[ego.lane_index],
                ego_s=float(ego.lane.local_coordinates(ego.position)[0]),
                ego_speed=float(ego.speed),
                spawn_lanes=(flat[("a", "b", 0)], flat[("a", "b", 1)]),
                spawns=_SPAWNS,
                position_jitter=_POSITION_JITTER,
                speed_jitter=_SPEED_JITTER,
                merging_lane=flat[merging.lane_index],
                merging_s=float(merging.lane.local_coordinates(merging.position)[0]),
                merging_speed=float(merging.speed),
                merging_target_speed=float(merging.target_speed),
                delta=float(IDMVehicle.DELTA),
                obstacle_lane=flat[obstacle.lane_index],
                obstacle_x=float(obstacle.position[0]),
                obstacle_y=float(obstacle.position[1]),
                obstacle_length=float(obstacle.LENGTH),
                obstacle_width=float(obstacle.WIDTH),
                others_check_collisions=all(v.check_collisions for v in road.vehicles),
            ),
            reward=MergeReward(
                collision_reward=float(config["collision_reward"]),
                right_lane_reward=float(config["right_lane_reward"]),
                high_speed_reward=float(config["high_speed_reward"]),
                lane_change_reward=float(config["lane_change_reward"]),
                merging_speed_reward=float(config["merging_speed_reward"]),
                reward_speed_range=tuple(float(s) for s in config["reward_speed_range"]),
                merge_lane=flat[("b", "c", 2)],
                terminal_x=_TERMINAL_X,
            ),
            observation=observation_params(core),
        )
    finally:
        env.close()
