"""``HighwayEnv``'s reward, its components, and the episode's end.

Components: ``collision_reward`` (the ego's crash flag), ``right_lane_reward`` (the
ego's TARGET lane over ``lanes_count - 1``), ``high_speed_reward`` (forward speed
``speed cos(heading)`` mapped from ``reward_speed_range`` to [0, 1], clipped) and
``on_road_reward``. The reward is their weighted sum, mapped to [0, 1] by
``normalize_reward``, times the on-road flag. An episode terminates when the ego
crashes (or leaves the road, with ``offroad_terminal``) and is truncated once
``time >= duration``.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("highway-fast-v0")
    >>> v = empty_world(1, 2, torch.float64).vehicles
    >>> v = v._replace(speed=torch.full((1, 2), 30.0, dtype=torch.float64),
    ...                target_lane=torch.full((1, 2), 2), lane=torch.full((1, 2), 2),
    ...                y=torch.full((1, 2), 8.0, dtype=torch.float64))
    >>> r, parts, term = reward(v, params)
    >>> round(float(r), 6), bool(term)
    (1.0, False)
    >>> [round(float(t), 6) for t in parts.values()]  # collision, right lane, speed, on road
    [0.0, 1.0, 1.0, 1.0]
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.road import on_lane
from torchrl_grpo.sim.state import Vehicles

__all__ = ["REWARD_COMPONENTS", "reward", "truncated"]

#: The components, in ``HighwayEnv._rewards``'s order.
REWARD_COMPONENTS = ("collision_reward", "right_lane_reward", "high_speed_reward", "on_road_reward")


def reward(
    v: Vehicles, params: HighwayParams
) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
    """The ego's reward, reward components and termination flag, ``[B]`` each.

    Args:
        v: the vehicle table after the step.
        params: the constants.

    Returns:
        ``(reward, components, terminated)``.

    Example:
        >>> # see the module's example
    """
    r = params.reward
    x, y, heading, speed = v.x[:, 0], v.y[:, 0], v.heading[:, 0], v.speed[:, 0]
    crashed = v.crashed[:, 0]
    road_ok = on_lane(x, y, v.lane[:, 0], params.road)
    lanes = params.road.lanes_count
    forward = speed * torch.cos(heading)
    low, high = r.reward_speed_range
    scaled = 0 + (forward - low) * (1 - 0) / (high - low)
    parts = {
        "collision_reward": crashed.to(x.dtype),
        "right_lane_reward": v.target_lane[:, 0].to(x.dtype) / max(lanes - 1, 1),
        "high_speed_reward": torch.clamp(scaled, 0, 1),
        "on_road_reward": road_ok.to(x.dtype),
    }
    weights = {
        "collision_reward": r.collision_reward,
        "right_lane_reward": r.right_lane_reward,
        "high_speed_reward": r.high_speed_reward,
        "on_road_reward": r.on_road_reward,
    }
    total = torch.zeros_like(x)
    for name in REWARD_COMPONENTS:
        total = total + weights[name] * parts[name]
    if r.normalize_reward:
        best = r.high_speed_reward + r.right_lane_reward
        total = 0 + (total - r.collision_reward) * (1 - 0) / (best - r.collision_reward)
    total = total * parts["on_road_reward"]
    terminated = crashed | (r.offroad_terminal & ~road_ok)
    return total, parts, terminated


def truncated(time: torch.Tensor, params: HighwayParams) -> torch.Tensor:
    """``time >= duration``.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> time = torch.tensor([29.0, 30.0], dtype=torch.float64)
        >>> truncated(time, tensor_params("highway-fast-v0"))
        tensor([False,  True])
    """
    return time >= params.reward.duration
