"""New worlds, drawn as ``HighwayEnv._create_vehicles`` draws them.

The ego first (speed ``ego_speed``, lane ``initial_lane_id`` or uniform, spacing
``ego_spacing``), then each other vehicle in turn: a uniform lane, a speed uniform in
``[speed_low, speed_high] * speed_limit``, a position ``offset * uniform(jitter)``
ahead of the frontmost vehicle so far (the rearmost starts ``first_offsets *
offset`` in), with ``offset = spacing (spacing_base + spacing_per_speed * speed)
exp(-spacing_decay * lanes_count)``, and an IDM exponent uniform in ``delta_range``.
MOBIL timers start at ``((x + y) pi) mod lane_change_delay``, targets at the initial
lane and speed; the ego's target speed is the target speed nearest 25 m/s.

The draws come from each world's own counter-based stream (:mod:`.rng`), not from
numpy's generator: the distribution is highway-env's, the individual worlds are not.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.state import empty_world
    >>> from torchrl_grpo.sim.rng import seed_keys
    >>> params = tensor_params("highway-fast-v0")
    >>> world = empty_world(4, params.num_vehicles, torch.float64)
    >>> world = world._replace(rng_key=seed_keys(torch.arange(4), 0))
    >>> new = reset_world(world, torch.tensor([True, True, False, True]), params)
    >>> new.rng_counter.tolist(), bool((new.vehicles.x[:, 1:] > new.vehicles.x[:, :1]).all())
    ([1, 1, 0, 1], False)
    >>> bool((new.vehicles.x[[0, 1, 3], 1:] > new.vehicles.x[[0, 1, 3], :1]).all())
    True
"""

from __future__ import annotations

import math

import torch

from torchrl_grpo.sim.control import speed_to_index
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.rng import uniform
from torchrl_grpo.sim.state import Vehicles, World

__all__ = ["reset_world"]


def _between(u: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """Numpy's ``Generator.uniform(low, high)`` from a draw in [0, 1)."""
    return low + (high - low) * u


def reset_world(world: World, mask: torch.Tensor, params: HighwayParams) -> World:
    """``world`` with the rows of ``mask`` replaced by fresh episodes.

    On a CPU only the masked rows are drawn (a training step resets a few rows of
    thousands: drawing every row cost a third of a step at B = 8,192), and written
    back with ``index_copy``; on a GPU every row is drawn and selected with ``where``,
    which needs no host sync. The values are the same either way: each row's draws
    come from its own stream.

    Args:
        world: B worlds (their ``rng_key``/``rng_counter`` feed the draws).
        mask: ``[B]`` bool, the rows to reset.
        params: the constants.

    Returns:
        The new :class:`World`; unmasked rows are untouched, reset rows' counters advance.

    Example:
        >>> # see the module's example
    """
    v_old = world.vehicles
    if mask.device.type == "cuda":
        fresh, ego_index, counter = _fresh_rows(world.rng_key, world.rng_counter, params)
        rows = mask.unsqueeze(-1)
        table = Vehicles(
            *(torch.where(rows, n.to(o.dtype), o) for n, o in zip(fresh, v_old, strict=True))
        )
        return World(
            vehicles=table,
            speed_index=torch.where(mask, ego_index, world.speed_index),
            time=torch.where(mask, torch.zeros_like(world.time), world.time),
            steps=torch.where(mask, torch.zeros_like(world.steps), world.steps),
            rng_key=world.rng_key,
            rng_counter=torch.where(mask, counter, world.rng_counter),
        )
    at = mask.nonzero().squeeze(-1)
    fresh, ego_index, counter = _fresh_rows(
        world.rng_key.index_select(0, at), world.rng_counter.index_select(0, at), params
    )

    def put(old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        return old.index_copy(0, at, new.to(old.dtype))

    return World(
        vehicles=Vehicles(*(put(o, n) for n, o in zip(fresh, v_old, strict=True))),
        speed_index=put(world.speed_index, ego_index),
        time=world.time.index_fill(0, at, 0.0),
        steps=world.steps.index_fill(0, at, 0),
        rng_key=world.rng_key,
        rng_counter=put(world.rng_counter, counter),
    )


def _fresh_rows(
    key: torch.Tensor, counter: torch.Tensor, params: HighwayParams
) -> tuple[Vehicles, torch.Tensor, torch.Tensor]:
    """Fresh episodes for the streams ``(key, counter)`` (``[R]`` each).

    Returns:
        ``(vehicle table [R, N] in float64, the ego's speed index, the advanced counters)``.
    """
    t, road = params.traffic, params.road
    n_lanes, others = road.lanes_count, t.vehicles_count
    device = key.device
    u, counter = uniform(key, counter, 2 + 4 * others)
    ego_lane_u, ego_jitter = u[:, 0], u[:, 1]
    lane_u, speed_u, jitter_u, delta_u = u[:, 2:].view(-1, others, 4).unbind(-1)
    decay = math.exp(-t.spacing_decay * n_lanes)
    if t.initial_lane_id is None:
        ego_lane = torch.floor(ego_lane_u * n_lanes).to(torch.int64)
    else:
        ego_lane = torch.full_like(key, int(t.initial_lane_id))
    ego_offset = t.ego_spacing * (t.spacing_base + t.spacing_per_speed * t.ego_speed) * decay
    ego_x = t.first_offsets * ego_offset + ego_offset * _between(ego_jitter, *t.jitter)
    limit = road.speed_limit
    speeds = _between(speed_u, t.speed_low * limit, t.speed_high * limit)
    offsets = (1 / t.vehicles_density) * (t.spacing_base + t.spacing_per_speed * speeds) * decay
    steps_ahead = offsets * _between(jitter_u, *t.jitter)
    xs = ego_x.unsqueeze(-1) + torch.cumsum(steps_ahead, dim=-1)
    lanes = torch.floor(lane_u * n_lanes).to(torch.int64)
    deltas = _between(delta_u, *params.idm.delta_range)
    x = torch.cat([ego_x.unsqueeze(-1), xs], dim=-1)
    lane = torch.cat([ego_lane.unsqueeze(-1), lanes], dim=-1)
    y = lane.to(torch.float64) * road.lane_width
    speed = torch.cat([torch.full_like(ego_x, t.ego_speed).unsqueeze(-1), speeds], dim=-1)
    ego_index = speed_to_index(torch.full_like(ego_x, t.ego_speed), params.control.target_speeds)
    ego_target = torch.tensor(params.control.target_speeds, dtype=torch.float64, device=device)[
        ego_index
    ]
    target_speed = torch.cat([ego_target.unsqueeze(-1), speeds], dim=-1)
    timer = torch.remainder((x + y) * math.pi, params.idm.lane_change_delay)
    timer[:, 0] = 0.0
    delta = torch.cat([torch.zeros_like(ego_x).unsqueeze(-1), deltas], dim=-1)
    zeros = torch.zeros_like(x)
    checks = torch.full_like(lane, t.others_check_collisions, dtype=torch.bool)
    checks[:, 0] = True
    fresh = Vehicles(
        x=x, y=y, heading=zeros, speed=speed, target_speed=target_speed,
        steering=zeros, acceleration=zeros, timer=timer, delta=delta,
        impact_x=zeros, impact_y=zeros, lane=lane, target_lane=lane,
        crashed=torch.zeros_like(checks), impact=torch.zeros_like(checks),
        check_collisions=checks, present=torch.ones_like(checks),
    )  # fmt: skip
    return fresh, ego_index, counter
