"""What a roundabout-v0 step reports: the absolute Kinematics table, the speed-index reward.

The observation is merge-v0's (:mod:`.merge_output`: the vehicles closer than the
perception distance and less than two lengths behind along the ego's current lane,
sorted by that distance), with the roundabout's ``absolute`` rows and fixed ranges.

The reward is ``RoundaboutEnv._reward``: ``collision * crashed + high_speed *
speed_index / 2 + lane_change * (action is a lane change) + on_road_reward * on_road``
(the config's weights; ``on_road_reward`` is 0 by default), summed in ``_rewards``'
order, mapped by ``lmap`` from ``[collision, high_speed]`` to ``[0, 1]``, then times
the on-road flag (the ego within its current lane's width). An episode terminates on
a crash and is truncated at ``duration``.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.roundabout_reset import DRAWS, reset_roundabout
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("roundabout-v0")
    >>> world = empty_world(1, params.num_vehicles, torch.float64, route_length=params.route_length)
    >>> draws = torch.zeros(1, DRAWS, dtype=torch.float64)
    >>> world = reset_roundabout(world, torch.ones(1, dtype=torch.bool), draws, params)
    >>> out = observe_roundabout(world, params, torch.tensor([1]))
    >>> [round(v, 4) for v in out["observation"][0, 0].tolist()]  # the ego at (2, 45), 8 m/s south
    [1.0, 0.02, 0.45, 0.0, -0.5333]
    >>> round(float(out["reward"][0]), 4)  # (0.2 * 1 / 2 + 1) / 1.2
    0.9167
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim.merge_output import ego_on_road, outputs
from torchrl_grpo.sim.observation import route_intentions
from torchrl_grpo.sim.roundabout_params import RoundaboutParams

__all__ = ["ROUNDABOUT_REWARD_COMPONENTS", "observe_roundabout", "roundabout_reward"]

#: ``RoundaboutEnv._rewards``' keys, in its order.
ROUNDABOUT_REWARD_COMPONENTS = (
    "collision_reward",
    "high_speed_reward",
    "lane_change_reward",
    "on_road_reward",
)


def roundabout_reward(
    world, params: RoundaboutParams, action: torch.Tensor | None, on_road: torch.Tensor
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """``(reward, components)`` of B roundabout worlds after ``action`` (``None``: no action yet).

    Example:
        >>> # see the module's example
    """
    r = params.reward
    v = world.vehicles
    dtype = v.speed.dtype
    if action is None:
        changed = torch.zeros_like(v.crashed[:, 0])
    else:
        changed = (action == 0) | (action == 2)
    parts = {
        "collision_reward": v.crashed[:, 0].to(dtype),
        "high_speed_reward": world.speed_index.to(dtype) / r.speed_levels,
        "lane_change_reward": changed.to(dtype),
        "on_road_reward": on_road.to(dtype),
    }
    weights = {
        "collision_reward": r.collision_reward,
        "high_speed_reward": r.high_speed_reward,
        "lane_change_reward": r.lane_change_reward,
        "on_road_reward": r.on_road_reward,
    }
    total = torch.zeros_like(v.speed[:, 0])
    for name in ROUNDABOUT_REWARD_COMPONENTS:
        total = total + weights[name] * parts[name]
    if r.normalize_reward:
        low, high = r.collision_reward, r.high_speed_reward
        total = 0 + (total - low) * (1 - 0) / (high - low)
    return total * parts["on_road_reward"], parts


def observe_roundabout(
    world, params: RoundaboutParams, action: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    """What an env step reports of B roundabout worlds (the keys of ``observe_world``).

    Args:
        world: B roundabout worlds.
        params: the constants.
        action: the step's ``[B]`` actions (the lane-change term), ``None`` at reset.

    Returns:
        ``observation``, ``reward``, ``terminated``, ``truncated``, ``crashed``,
        ``on_road``, ``speed``, ``ego_position``, ``ego_heading``, ``reward_components``.

    Example:
        >>> # see the module's example
    """
    v = world.vehicles
    on_road = ego_on_road(v, params)
    total, parts = roundabout_reward(world, params, action, on_road)
    truncated = world.time >= params.reward.duration
    intentions = route_intentions(world, params)
    return outputs(v, params, total, parts, v.crashed[:, 0], truncated, on_road, intentions)
