"""One env step of B worlds: ``frames`` substeps of act, move and collide, then the outputs.

A substep is ``AbstractEnv._simulate``'s frame:

1. on an env step's first frame, the ego's meta-action sets its target lane or speed;
2. ``road.act()``: the ego computes its steering and speed commands; every other
   vehicle that has not crashed runs MOBIL (:mod:`.mobil`) and IDM (:mod:`.idm`)
   against the substep's lane index (:mod:`.neighbours`);
3. ``road.step(dt)``: every vehicle moves (:mod:`.kinematics`), then pairs collide
   (:mod:`.collision`).

:func:`step` and :func:`observe_world` are pure functions of tensors: the env class
calls them eagerly or through ``torch.compile``.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.rng import seed_keys
    >>> from torchrl_grpo.sim.reset import reset_world
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("highway-fast-v0")
    >>> world = empty_world(8, params.num_vehicles, torch.float32)
    >>> world = reset_world(world._replace(rng_key=seed_keys(torch.arange(8), 0)),
    ...                     torch.ones(8, dtype=torch.bool), params)
    >>> world, out = step(world, torch.full((8,), 1), params)
    >>> out["observation"].shape, world.time.tolist()[:2], world.steps.tolist()[:2]
    (torch.Size([8, 5, 5]), [1.0, 1.0], [5, 5])
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from torchrl_grpo.sim.collision import collide
from torchrl_grpo.sim.control import apply_meta_action, steering_control
from torchrl_grpo.sim.idm import gather_car, interaction
from torchrl_grpo.sim.kinematics import step_vehicles
from torchrl_grpo.sim.mobil import drivers_of, lane_change_policy
from torchrl_grpo.sim.neighbours import lane_index, neighbours
from torchrl_grpo.sim.observation import observe
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.reward import reward, truncated
from torchrl_grpo.sim.selection import scatter, select
from torchrl_grpo.sim.state import Vehicles, World, take

__all__ = ["Stages", "act", "compiled_stages", "eager_stages", "observe_world", "step", "substep"]


class Stages(NamedTuple):
    """The stages of a step that compute every vehicle, with no data-dependent shapes.

    :func:`step` calls them eagerly by default (:func:`eager_stages`); on a CPU,
    :func:`compiled_stages` runs them through ``torch.compile``, where Inductor fuses
    each into a few C++ loops, while the compacted stages (MOBIL's due vehicles, the
    close pairs of the collision pass) stay eager: compiling those densely computes
    every vehicle's decision and is slower than eager on a CPU (docs/sim.md, "Speed").

    Attributes:
        drivers: ``(v, params) -> (lane index, Drivers)``: the lane index and IDM.
        steering: :func:`~torchrl_grpo.sim.control.steering_control`.
        move: :func:`~torchrl_grpo.sim.kinematics.step_vehicles`.
        observe: :func:`observe_world`.
    """

    drivers: Callable
    steering: Callable
    move: Callable
    observe: Callable


def _set_ego(v: Vehicles, **columns: torch.Tensor) -> Vehicles:
    """``v`` with row 0 of the given columns replaced."""
    out = {}
    for name, value in columns.items():
        column = getattr(v, name).clone()
        column[:, 0] = value
        out[name] = column
    return v._replace(**out)


def _drivers(v: Vehicles, params: HighwayParams) -> tuple:
    """The substep's lane index and every vehicle's IDM terms."""
    index = lane_index(v.x, v.y, v.present, params.road)
    return index, drivers_of(v, index, params)


def act(
    v: Vehicles, params: HighwayParams, dense: bool = False, stages: Stages | None = None
) -> Vehicles:
    """``road.act()``: every vehicle's commands (and the others' lane decisions).

    Args:
        v: the vehicle table, the ego's targets already set for this substep.
        params: the constants.
        dense: compute every vehicle with masks instead of compacting (see
            :mod:`.selection`).
        stages: the dense stages (default :func:`eager_stages`).

    Returns:
        The table with new ``steering``, ``acceleration``, ``target_lane`` and ``timer``.

    Example:
        >>> # see the module's example
    """
    stages = stages or EAGER
    index, drivers = stages.drivers(v, params)
    target, timer = lane_change_policy(v, drivers, index, params, dense)
    acc = drivers.acc
    sel = select(v.lane != target, dense)
    if not sel.empty:
        # While changing lanes, IDM also brakes for the front vehicle of the target lane.
        target_front, _ = neighbours(index, sel.rows, sel.vehicle, take(target, sel.at))
        me = gather_car(drivers.table, sel.rows, sel.vehicle)._replace(exists=None)
        ahead = gather_car(drivers.table, sel.rows, target_front)
        acc_target = take(drivers.free, sel.at) - interaction(me, ahead, params)
        acc = scatter(acc, sel, torch.minimum(take(acc, sel.at), acc_target))
    acc = torch.clamp(acc, -params.idm.acc_max, params.idm.acc_max)
    steer = stages.steering(v.x, v.y, v.speed, v.heading, target, params)
    ego_acc = params.control.kp_a * (v.target_speed[:, 0] - v.speed[:, 0])

    others = v.present & ~v.crashed
    others[:, 0] = False
    ego = torch.zeros_like(others)
    ego[:, 0] = True
    return v._replace(
        steering=torch.where(others | ego, steer, v.steering),
        acceleration=torch.where(others, acc, _set_ego(v, acceleration=ego_acc).acceleration),
        target_lane=torch.where(others, target, v.target_lane),
        timer=timer,
    )


def substep(
    world: World,
    action: torch.Tensor,
    params: HighwayParams,
    dense: bool = False,
    stages: Stages | None = None,
) -> World:
    """One simulation frame; ``action`` applies where ``steps`` is a multiple of ``frames``.

    Args:
        world: B worlds.
        action: ``[B]`` int64 meta-actions (-1: none).
        params: the constants.
        dense: see :func:`act`.
        stages: see :func:`act`.

    Returns:
        The worlds one frame later.

    Example:
        >>> # see the module's example
    """
    v = world.vehicles
    first = torch.remainder(world.steps, params.time.frames) == 0
    action = torch.where(first, action, torch.full_like(action, -1))
    lane, index, speed = apply_meta_action(
        v.x[:, 0], v.y[:, 0], v.speed[:, 0], v.target_lane[:, 0], v.target_speed[:, 0],
        world.speed_index, action, params,
    )  # fmt: skip
    v = _set_ego(v, target_lane=lane, target_speed=speed)
    v = act(v, params, dense, stages)
    v = (stages or EAGER).move(v, params)
    v = collide(v, params, dense)
    return world._replace(vehicles=v, speed_index=index, steps=world.steps + 1)


def observe_world(
    world: World, params: HighwayParams, observation: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    """What an env step reports of the worlds (without advancing them).

    Args:
        world: B worlds.
        params: the constants.
        observation: the Kinematics table if already computed (the C++ step's).

    Returns:
        ``observation``, ``reward``, ``terminated``, ``truncated``, ``crashed``,
        ``on_road``, ``speed``, ``ego_position``, ``ego_heading`` and
        ``reward_components`` (a dict), each with a leading ``[B]``.

    Example:
        >>> # see the module's example
    """
    v = world.vehicles
    total, parts, terminated = reward(v, params)
    return {
        "observation": observe(v, params) if observation is None else observation,
        "reward": total,
        "terminated": terminated,
        "truncated": truncated(world.time, params),
        "crashed": v.crashed[:, 0],
        "on_road": parts["on_road_reward"] > 0,
        "speed": v.speed[:, 0],
        "ego_position": torch.stack([v.x[:, 0], v.y[:, 0]], dim=-1),
        "ego_heading": v.heading[:, 0],
        "reward_components": parts,
    }


def step(
    world: World,
    action: torch.Tensor,
    params: HighwayParams,
    dense: bool = False,
    stages: Stages | None = None,
    frame: Callable = substep,
) -> tuple[World, dict[str, torch.Tensor]]:
    """``env.step(action)`` for B worlds.

    Args:
        world: B worlds.
        action: ``[B]`` int64 meta-actions.
        params: the constants.
        dense: static shapes throughout (for ``torch.compile`` and GPUs), see
            :mod:`.selection`; the same values as the default compacted path.
        stages: the dense stages (default :func:`eager_stages`; see :class:`Stages`).
        frame: the substep, called ``params.time.frames`` times (:func:`substep`, or
            one compiled substep: compiling the whole step unrolls its frames into one
            graph that Inductor takes minutes to lower).

    Returns:
        ``(worlds after the step, observe_world of them)``.

    Example:
        >>> # see the module's example
    """
    world = world._replace(time=world.time + params.time.step_time)
    stages = stages or EAGER
    for _ in range(params.time.frames):
        world = frame(world, action, params, dense, stages)
    return world, stages.observe(world, params)


def eager_stages() -> Stages:
    """The dense stages as plain functions (what :func:`step` uses by default).

    Example:
        >>> eager_stages().move.__name__
        'step_vehicles'
    """
    return Stages(_drivers, steering_control, step_vehicles, observe_world)


def compiled_stages(**kwargs: Any) -> Stages:
    """The dense stages, each through ``torch.compile(..., **kwargs)`` (static shapes).

    Each compiles on its first call, once per batch size and dtype. On a CPU Inductor
    emits C++ whose values matched the eager ones bit for bit in float32 and float64
    (tests/envs/test_tensor_compile.py).

    Example:
        >>> stages = compiled_stages(backend="eager")  # traces only: no code generation
        >>> isinstance(stages, Stages)
        True
    """
    kwargs.setdefault("dynamic", False)
    return Stages(*(torch.compile(fn, **kwargs) for fn in eager_stages()))


EAGER = eager_stages()
