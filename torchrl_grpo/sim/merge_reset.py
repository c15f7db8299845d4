"""Fresh merge-v0 worlds from their reset draws: ``MergeEnv._make_vehicles`` in tensors.

highway-env draws a merge reset from the env's generator (PCG64) in a fixed order: for
each of the three highway cars, ``integers(2)`` (its lane), ``uniform(-5, 5)`` (added
to its position) and ``uniform(-1, 1)`` (added to its speed). The env package replays
those 9 draws with numpy on the host (``torchrl_grpo.envs.highway.merge_draws``), so
that a world reset with the generator of ``reset(seed=s)`` IS highway-env's world of
seed ``s``; this module builds the worlds from them: the ego at its spawn, the three
cars, the merging car at its spawn with its target speed, and the obstacle, each on
its closest lane with ``timer = (sum(position) * pi) % lane_change_delay``.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("merge-v0")
    >>> world = empty_world(1, params.num_vehicles, torch.float64)
    >>> draws = torch.tensor([[1.0, 0.5, 0.0, 0.0, -1.0, 0.25, 1.0, 0.0, 0.0]], dtype=torch.float64)
    >>> world = reset_merge(world, torch.ones(1, dtype=torch.bool), draws, params)
    >>> world.vehicles.x[0].tolist(), world.vehicles.lane[0].tolist()
    ([30.0, 90.5, 69.0, 5.0, 110.0, 310.0], [1, 1, 0, 1, 7, 4])
"""

from __future__ import annotations

import math

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.control import speed_to_index
from torchrl_grpo.sim.fresh_rows import put_rows
from torchrl_grpo.sim.merge_params import MergeParams
from torchrl_grpo.sim.state import Vehicles, World

__all__ = ["DRAWS", "reset_merge"]

#: Reset draws per world: (lane, position offset, speed offset) per highway car.
DRAWS = 9


def reset_merge(
    world: World, rows: torch.Tensor, draws: torch.Tensor, params: MergeParams
) -> World:
    """``world`` with rows ``rows`` replaced by fresh merge worlds built from ``draws``.

    Args:
        world: B worlds (their rows outside ``rows`` are kept).
        rows: ``[B]`` bool, the worlds to reset.
        draws: ``[B, 9]`` float64: per highway car, ``integers(2)`` (as a float), then
            ``uniform(-5, 5)`` and ``uniform(-1, 1)``.
        params: the constants.

    Returns:
        The worlds, ``time`` and ``steps`` 0 and the ego's speed index set on ``rows``.

    Example:
        >>> # see the module's example
    """
    v = world.vehicles
    t = params.traffic
    device = v.x.device
    n = v.x.shape[1]
    if draws.dtype != torch.float64:
        # A float32 draw would move every car by up to 4e-6 m: not highway-env's world.
        raise ValueError(f"merge reset draws must be float64, got {draws.dtype}")
    # Only the reset rows are built (a few of a batch each step), then put in place.
    reset = rows.to(device).nonzero().squeeze(-1)
    if reset.numel() == 0:
        return world
    draws = draws.to(device)[reset]
    batch = reset.numel()
    geo = params.road.lanes
    f64 = dict(dtype=torch.float64, device=device)

    spawn = torch.tensor(t.spawn_lanes, device=device)
    lane_col = [torch.full((batch,), t.ego_lane, device=device)]
    s_col = [torch.full((batch,), t.ego_s, **f64)]
    speed_col = [torch.full((batch,), t.ego_speed, **f64)]
    for k, (s0, v0) in enumerate(t.spawns):
        lane_col.append(spawn[draws[:, 3 * k].to(torch.int64)])
        s_col.append(s0 + draws[:, 3 * k + 1])
        speed_col.append(v0 + draws[:, 3 * k + 2])
    lane_col.append(torch.full((batch,), t.merging_lane, device=device))
    s_col.append(torch.full((batch,), t.merging_s, **f64))
    speed_col.append(torch.full((batch,), t.merging_speed, **f64))
    spawn_lane = torch.stack(lane_col, 1)
    x, y = L.position(torch.stack(s_col, 1), torch.zeros(batch, n - 1, **f64), spawn_lane, geo)
    x = torch.cat([x, torch.full((batch, 1), t.obstacle_x, **f64)], 1)
    y = torch.cat([y, torch.full((batch, 1), t.obstacle_y, **f64)], 1)
    heading = torch.zeros(batch, n, **f64)
    speed = torch.cat([torch.stack(speed_col, 1), torch.zeros(batch, 1, **f64)], 1)
    lane = L.closest_lane(x, y, heading, geo)
    lane[:, -1] = t.obstacle_lane
    target_speed = speed.clone()
    index = speed_to_index(speed[:, 0], params.control.target_speeds)
    speeds = torch.tensor(params.control.target_speeds, **f64)
    target_speed[:, 0] = speeds[index]
    target_speed[:, -2] = t.merging_target_speed
    timer = torch.remainder((x + y) * math.pi, params.idm.lane_change_delay)
    timer[:, 0] = 0.0
    timer[:, -1] = 0.0
    delta = torch.full((batch, n), t.delta, **f64)
    delta[:, 0] = 0.0
    delta[:, -1] = 0.0
    zeros = torch.zeros(batch, n, **f64)
    flags = torch.zeros(batch, n, dtype=torch.bool, device=device)
    fresh = Vehicles(
        x=x, y=y, heading=heading, speed=speed, target_speed=target_speed, steering=zeros,
        acceleration=zeros, timer=timer, delta=delta, impact_x=zeros, impact_y=zeros,
        lane=lane, target_lane=lane.clone(), crashed=flags, impact=flags,
        check_collisions=torch.ones_like(flags), present=torch.ones_like(flags),
    )  # fmt: skip
    return put_rows(world, reset, fresh, index)
