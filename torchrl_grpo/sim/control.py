"""The low-level controllers of ``ControlledVehicle`` and the ego's meta-actions.

Every vehicle steers towards the centre of its target lane with the same cascade
(lateral position -> lateral speed -> heading -> heading rate -> steering); the ego
tracks its target speed with a proportional controller, and its meta-actions
(``MDPVehicle.act``) move the target lane or the target speed index.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> params = tensor_params("highway-fast-v0")
    >>> z = torch.zeros(1, dtype=torch.float64)
    >>> steer = steering_control(z, z + 2.0, z + 25.0, z, torch.tensor([1]), params)
    >>> bool(steer > 0)  # 2 m left of lane 1's centre: steer right (towards +y)
    True
"""

from __future__ import annotations

import math

import torch

from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.road import is_reachable, lateral, not_zero, wrap_to_pi

__all__ = [
    "FASTER",
    "IDLE",
    "LANE_LEFT",
    "LANE_RIGHT",
    "SLOWER",
    "apply_meta_action",
    "speed_to_index",
    "steer_to",
    "steering_control",
]

#: ``DiscreteMetaAction.ACTIONS_ALL``'s indices.
LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = 0, 1, 2, 3, 4


def steering_control(
    x: torch.Tensor,
    y: torch.Tensor,
    speed: torch.Tensor,
    heading: torch.Tensor,
    target_lane: torch.Tensor,
    params: HighwayParams,
) -> torch.Tensor:
    """``ControlledVehicle.steering_control(target_lane)``, clipped to the steering range.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> z = torch.zeros(1, dtype=torch.float64)
        >>> float(steering_control(z, z, z + 20.0, z, torch.tensor([0]), params))
        0.0
    """
    return steer_to(lateral(y, target_lane, params.road), 0.0, speed, heading, params)


def steer_to(
    lat: torch.Tensor,
    lane_heading: torch.Tensor | float,
    speed: torch.Tensor,
    heading: torch.Tensor,
    params: HighwayParams,
) -> torch.Tensor:
    """The steering cascade from a lateral offset and the lane's look-ahead heading.

    ``ControlledVehicle.steering_control`` after its lane look-ups: ``lat`` is the
    vehicle's lateral coordinate in the target lane, ``lane_heading`` that lane's
    heading at ``s + speed * tau_pursuit`` (``0.0`` on straight lanes along x).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> z = torch.zeros(1, dtype=torch.float64)
        >>> float(steer_to(z, 0.0, z + 20.0, z, params))
        0.0
    """
    c = params.control
    speed_nz = not_zero(speed)
    lateral_speed_command = -c.kp_lateral * lat
    heading_command = torch.asin(torch.clamp(lateral_speed_command / speed_nz, -1, 1))
    # The lane's heading plus the clipped command, as highway-env adds them.
    heading_ref = lane_heading + torch.clamp(heading_command, -math.pi / 4, math.pi / 4)
    heading_rate_command = c.kp_heading * wrap_to_pi(heading_ref - heading)
    slip = params.vehicle.length / 2 / speed_nz * heading_rate_command
    slip_angle = torch.asin(torch.clamp(slip, -1, 1))
    steering = torch.atan(2 * torch.tan(slip_angle))
    return torch.clamp(steering, -c.max_steering_angle, c.max_steering_angle)


def speed_to_index(speed: torch.Tensor, target_speeds: tuple[float, ...]) -> torch.Tensor:
    """``MDPVehicle.speed_to_index``: the nearest target speed's index (half to even).

    Example:
        >>> speed = torch.tensor([19.0, 25.0, 27.6], dtype=torch.float64)
        >>> speed_to_index(speed, (20.0, 25.0, 30.0))
        tensor([0, 1, 2])
    """
    n = len(target_speeds)
    x = (speed - target_speeds[0]) / (target_speeds[-1] - target_speeds[0])
    return torch.clamp(torch.round(x * (n - 1)), 0, n - 1).to(torch.int64)


def apply_meta_action(
    x: torch.Tensor,
    y: torch.Tensor,
    speed: torch.Tensor,
    target_lane: torch.Tensor,
    target_speed: torch.Tensor,
    speed_index: torch.Tensor,
    action: torch.Tensor,
    params: HighwayParams,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ego's new target lane, speed index and target speed after a meta-action.

    ``FASTER``/``SLOWER`` move one index from the index of the CURRENT speed (not the
    target); a lane change moves the TARGET lane by one if that lane is reachable.

    Args:
        x: ``[B]`` the ego's position along the road.
        y: ``[B]`` lateral position.
        speed: ``[B]`` speed.
        target_lane: ``[B]`` target lane.
        target_speed: ``[B]`` target speed.
        speed_index: ``[B]`` index of the target speed.
        action: ``[B]`` int64 meta-action (0 LANE_LEFT, 1 IDLE, 2 LANE_RIGHT, 3 FASTER,
            4 SLOWER); -1 leaves a row untouched.
        params: the constants.

    Returns:
        ``(target_lane, speed_index, target_speed)``.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> f = lambda *v: torch.tensor(v, dtype=torch.float64)
        >>> lane, idx, ts = apply_meta_action(f(10.0, 10.0), f(0.0, 0.0), f(25.0, 25.0),
        ...     torch.tensor([0, 0]), f(25.0, 25.0), torch.tensor([1, 1]),
        ...     torch.tensor([LANE_RIGHT, FASTER]), params)
        >>> lane.tolist(), idx.tolist(), ts.tolist()
        ([1, 0], [1, 2], [25.0, 30.0])
    """
    speeds = params.control.target_speeds
    lanes = params.road.lanes_count
    shift = torch.where(action == LANE_LEFT, -1, torch.where(action == LANE_RIGHT, 1, 0))
    candidate = torch.clamp(target_lane + shift, 0, lanes - 1)
    reachable = is_reachable(x, y, candidate, params.road)
    target_lane = torch.where((shift != 0) & reachable, candidate, target_lane)

    step = torch.where(action == FASTER, 1, torch.where(action == SLOWER, -1, 0))
    moved = torch.clamp(speed_to_index(speed, speeds) + step, 0, len(speeds) - 1)
    changes_speed = step != 0
    speed_index = torch.where(changes_speed, moved, speed_index)
    table = torch.tensor(speeds, dtype=speed.dtype, device=speed.device)
    target_speed = torch.where(changes_speed, table[moved], target_speed)
    return target_lane, speed_index, target_speed
