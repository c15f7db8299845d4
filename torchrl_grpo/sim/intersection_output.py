"""What an intersection-v0 step reports: the absolute Kinematics table, the arrival reward.

The observation is merge-v0's (:mod:`.merge_output`: the present vehicles closer than
the perception distance and less than two lengths behind along the ego's current
lane, sorted by that distance), with intersection-v0's absolute rows, its 15 rows and
its ``cos_h, sin_h`` features.

The reward is ``IntersectionEnv._agent_reward``: ``collision * crashed + high_speed *
clip(lmap(speed, reward_speed_range, [0, 1]), 0, 1) + arrived * arrived`` (summed in
``_agent_rewards``' order, the on-road term weighing 0), replaced by ``arrived_reward``
once arrived (on an exit lane, ``s >= 25`` m), times the on-road flag, then mapped from
``[collision, arrived]`` to ``[0, 1]`` if ``normalize_reward``. An episode terminates
on a crash or an arrival (or off the road with ``offroad_terminal``) and is truncated
at ``duration``.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.intersection_reset import empty_intersection, place_ego
    >>> params = tensor_params("intersection-v0")
    >>> world = empty_intersection(1, params)
    >>> one = torch.ones(1, dtype=torch.bool)
    >>> world = place_ego(world, one, torch.tensor([1]), torch.tensor([1.0]).double(), params)
    >>> out = observe_intersection(world, params)
    >>> [round(v, 4) for v in out["observation"][0, 0].tolist()]  # at (2, 46) m, 10 m/s to -y
    [1.0, 0.02, 0.46, 0.0, -0.5, 0.0, -1.0]
    >>> out["reward"].tolist()  # at 10 m/s: the full speed reward
    [1.0]
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.intersection_params import IntersectionParams
from torchrl_grpo.sim.merge_output import ego_on_road, outputs
from torchrl_grpo.sim.observation import route_intentions

__all__ = ["INTERSECTION_REWARD_COMPONENTS", "arrived", "observe_intersection"]

#: ``IntersectionEnv._agent_rewards``' keys, in its order.
INTERSECTION_REWARD_COMPONENTS = (
    "collision_reward",
    "high_speed_reward",
    "arrived_reward",
    "on_road_reward",
)


def arrived(world, params: IntersectionParams) -> torch.Tensor:
    """``has_arrived(ego)``: on an exit lane, at least ``arrive_distance`` along it.

    Example:
        >>> # see the module's example
    """
    v = world.vehicles
    lane = v.lane[:, 0]
    s, _ = L.local_coordinates(v.x[:, 0], v.y[:, 0], lane, params.road.lanes)
    exits = torch.tensor(params.road.exit, device=lane.device)[lane]
    return exits & (s >= params.traffic.arrive_distance)


def observe_intersection(world, params: IntersectionParams, action=None) -> dict[str, torch.Tensor]:
    """What an env step reports of B intersection worlds (the keys of ``observe_world``).

    Args:
        world: B intersection worlds.
        params: the constants.
        action: unused (the reward does not depend on it); for the common signature.

    Returns:
        ``observation``, ``reward``, ``terminated``, ``truncated``, ``crashed``,
        ``on_road``, ``speed``, ``ego_position``, ``ego_heading``, ``reward_components``.

    Example:
        >>> # see the module's example
    """
    del action
    r, v = params.reward, world.vehicles
    dtype = v.speed.dtype
    on_road = ego_on_road(v, params)
    crashed, done = v.crashed[:, 0], arrived(world, params)
    low, high = r.reward_speed_range
    scaled = 0 + (v.speed[:, 0] - low) * (1 - 0) / (high - low)
    parts = {
        "collision_reward": crashed.to(dtype),
        "high_speed_reward": torch.clamp(scaled, 0, 1),
        "arrived_reward": done.to(dtype),
        "on_road_reward": on_road.to(dtype),
    }
    weights = (r.collision_reward, r.high_speed_reward, r.arrived_reward, 0.0)
    total = torch.zeros_like(scaled)
    for name, weight in zip(INTERSECTION_REWARD_COMPONENTS, weights, strict=True):
        total = total + weight * parts[name]
    total = torch.where(done, torch.full_like(total, r.arrived_reward), total)
    total = total * parts["on_road_reward"]
    if r.normalize_reward:
        total = 0 + (total - r.collision_reward) * (1 - 0) / (r.arrived_reward - r.collision_reward)
    terminated = crashed | done
    if r.offroad_terminal:
        terminated = terminated | ~on_road
    truncated = world.time >= r.duration
    intentions = route_intentions(world, params)
    return outputs(v, params, total, parts, terminated, truncated, on_road, intentions)
