"""``Vehicle.step``: clip the commands, integrate the kinematic bicycle, apply impacts.

For every present vehicle, in one batched pass (a vehicle's step reads only its own
state):

- a crashed vehicle's commands become (steering 0, acceleration ``-speed``); beyond
  ``±max_speed`` the acceleration is clipped back towards it (speed itself is never
  clipped);
- ``beta = atan(tan(steering) / 2)``; position moves by ``speed (cos, sin)(heading +
  beta) dt``, then by a pending impact (which crashes the vehicle); heading turns by
  ``speed sin(beta) / (length / 2) dt``; speed gains ``acceleration dt``, all from the
  OLD speed and heading;
- the lane becomes the closest lane; other vehicles' MOBIL timers gain ``dt``.

Padding rows (``present`` False) are stepped too: nothing reads them.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("highway-fast-v0")
    >>> v = empty_world(1, 2, torch.float64).vehicles
    >>> v = v._replace(speed=torch.full((1, 2), 20.0, dtype=torch.float64),
    ...                acceleration=torch.full((1, 2), 1.0, dtype=torch.float64))
    >>> out = step_vehicles(v, params)
    >>> out.x.tolist(), out.speed.tolist(), out.timer.tolist()
    ([[4.0, 4.0]], [[20.2, 20.2]], [[0.0, 0.2]])
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.road import closest_lane
from torchrl_grpo.sim.state import Vehicles

__all__ = ["clip_commands", "step_vehicles"]


def clip_commands(v: Vehicles, params: HighwayParams) -> tuple[torch.Tensor, torch.Tensor]:
    """``Vehicle.clip_actions``: the (steering, acceleration) a step applies.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> from torchrl_grpo.sim.state import empty_world
        >>> params = tensor_params("highway-fast-v0")
        >>> v = empty_world(1, 1, torch.float64).vehicles
        >>> v = v._replace(speed=torch.tensor([[41.0]], dtype=torch.float64),
        ...                acceleration=torch.tensor([[3.0]], dtype=torch.float64))
        >>> [t.tolist() for t in clip_commands(v, params)]
        [[[0.0]], [[-1.0]]]
    """
    top, bottom = params.vehicle.max_speed, params.vehicle.min_speed
    steering = torch.where(v.crashed, torch.zeros_like(v.steering), v.steering)
    acc = torch.where(v.crashed, -1.0 * v.speed, v.acceleration)
    acc = torch.where(
        v.speed > top,
        torch.minimum(acc, 1.0 * (top - v.speed)),
        torch.where(v.speed < bottom, torch.maximum(acc, 1.0 * (bottom - v.speed)), acc),
    )
    return steering, acc


def step_vehicles(v: Vehicles, params: HighwayParams, closest: Callable | None = None) -> Vehicles:
    """Every present vehicle's ``step(dt)`` (the ego's included).

    Args:
        v: the vehicle table, with this substep's commands in ``steering`` and
            ``acceleration``.
        params: the constants.
        closest: ``(x, y, heading) -> lane`` on the scenario's road (default: the
            straight parallel lanes of :func:`~torchrl_grpo.sim.road.closest_lane`).

    Returns:
        The table after the substep; ``steering`` and ``acceleration`` hold the clipped
        commands that were applied, as highway-env keeps them in ``vehicle.action``.

    Example:
        >>> # see the module's example
    """
    dt = params.time.dt
    steering, acc = clip_commands(v, params)
    beta = torch.atan(0.5 * torch.tan(steering))
    x = v.x + (v.speed * torch.cos(v.heading + beta)) * dt
    y = v.y + (v.speed * torch.sin(v.heading + beta)) * dt
    # Padding rows move too: nothing reads them, and they stay finite.
    x = torch.where(v.impact, x + v.impact_x, x)
    y = torch.where(v.impact, y + v.impact_y, y)
    heading = v.heading + v.speed * torch.sin(beta) / (params.vehicle.length / 2) * dt
    timer = v.timer + dt
    timer[:, 0] = v.timer[:, 0]  # the ego has no MOBIL timer
    zero = torch.zeros_like(v.impact_x)
    return v._replace(
        x=x,
        y=y,
        heading=heading,
        speed=v.speed + acc * dt,
        steering=steering,
        acceleration=acc,
        impact_x=zero,
        impact_y=zero,
        lane=closest_lane(x, y, heading, params.road)
        if closest is None
        else closest(x, y, heading),
        crashed=v.crashed | v.impact,
        impact=torch.zeros_like(v.impact),
        timer=timer,
    )
