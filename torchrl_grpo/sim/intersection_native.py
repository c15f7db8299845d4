"""intersection-v0's frames in C++ (``intersection_rules.h``): a loop per world.

:func:`native_frames` is :func:`torchrl_grpo.sim.intersection.tensor_frames` in C++:
every vehicle's ``act()`` along its route (the roundabout's, ``routed_model.h``), the
right-of-way pass every ``regulation.every`` road frames
(:func:`~torchrl_grpo.sim.regulation.enforce_road_rules`), the motion, the closest lane
and the collisions in ``road.vehicles`` order. The step around it (the observation,
the exits, the spawns and their draws) stays the tensor path's: pass ``native_frames``
as ``frames`` to :func:`~torchrl_grpo.sim.intersection.intersection_step` and
:func:`~torchrl_grpo.sim.intersection.warm_up`. In float64 it agrees with the tensor
path to rounding (libm and torch round a sine differently, by an ulp), and it replays
its own bits after a restore.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import TensorHighwayEnv
    >>> from torchrl_grpo.sim.state import world_from_tensordict
    >>> env = TensorHighwayEnv("intersection-v0", num_envs=2, seed=0)
    >>> world = world_from_tensordict(env.reset()["state"])
    >>> after = native_frames(world, torch.tensor([4, 3]), 15, env.params)  # SLOWER, FASTER
    >>> (after.steps - world.steps).tolist(), (after.road_steps - world.road_steps).tolist()
    ([15, 15], [15, 15])
"""

from __future__ import annotations

import ctypes
import functools

import torch

from torchrl_grpo.sim.intersection_params import IntersectionParams
from torchrl_grpo.sim.native import NativeTable, with_columns, world_columns
from torchrl_grpo.sim.routed_native import load_routed_library, routed_road
from torchrl_grpo.sim.state import World

__all__ = ["native_frames", "rules_of"]

#: The most prediction times the C++ rule pass holds.
MAX_TIMES = 16


class RulesParams(ctypes.Structure):
    """The right-of-way constants, in ``intersection_rules.h``'s ``RulesParams`` order."""

    _fields_ = [
        ("every", ctypes.c_double),
        ("n_times", ctypes.c_double),
        ("rect_length", ctypes.c_double),
        ("rect_width", ctypes.c_double),
        ("times", ctypes.c_double * MAX_TIMES),
        ("priority", ctypes.c_void_p),
    ]


class _Rules:
    """The structure and the priority table its pointer addresses (kept alive together)."""

    def __init__(self, params: IntersectionParams) -> None:
        reg, car = params.regulation, params.vehicle
        if len(reg.times) > MAX_TIMES:
            raise ValueError(
                f"the C++ intersection step predicts at most {MAX_TIMES} times, "
                f"got {len(reg.times)}"
            )
        self.priority = torch.tensor(params.road.priority, dtype=torch.int64).contiguous()
        self.struct = RulesParams(
            float(reg.every), float(len(reg.times)), reg.length_scale * car.length,
            reg.width_scale * car.width, (ctypes.c_double * MAX_TIMES)(*reg.times),
            self.priority.data_ptr(),
        )  # fmt: skip


@functools.lru_cache(maxsize=16)
def rules_of(params: IntersectionParams) -> _Rules:
    """The right-of-way constants the C++ step reads (cached per params).

    The road's constants are :func:`~torchrl_grpo.sim.routed_native.routed_road`'s.

    Raises:
        ValueError: more prediction times than the C++ step holds.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> rules_of(tensor_params("intersection-v0")).struct.every
        7.0
    """
    return _Rules(params)


def native_frames(
    world: World,
    action: torch.Tensor,
    frames: int,
    params: IntersectionParams,
    threads: int | None = None,
) -> World:
    """``frames`` frames of B intersection worlds in C++; ``world`` is not modified.

    Args:
        world: B worlds on the CPU, with their routes and right-of-way state.
        action: ``[B]`` int64 meta-actions (SLOWER 4, IDLE 1, FASTER 3; -1: none), taken
            on a step's first frame.
        frames: the frames to run.
        params: intersection-v0's constants.
        threads: threads over the worlds (default ``torch.get_num_threads()``).

    Returns:
        The worlds after the frames.

    Raises:
        ValueError: a world off the CPU or without the intersection's state, an ego rank
            outside the table, negative ``frames``, or a config the C++ step cannot hold.
        NativeBuildError: see :func:`~torchrl_grpo.sim.routed_native.load_routed_library`.

    Example:
        >>> # see the module's example
    """
    if world.route is None or world.yielding is None:
        raise ValueError("the C++ intersection step needs worlds with routes and yield states")
    if frames < 0:
        raise ValueError(f"frames must be >= 0, got {frames}")
    rules = rules_of(params)
    road = routed_road(params)
    batch, n = world.vehicles.x.shape
    columns = world_columns(world, clone=True, routed=True)
    columns["action"] = action.to(torch.int64).contiguous()
    # The C++ code reads int64 legs, heads, frames and ranks, int8 yield states; copies of
    # what it writes, so that the input world stays as it was.
    legs = world.route.to(torch.int64).contiguous()
    heads = world.route_head.to(torch.int64).contiguous().clone()
    yielding = world.yielding.to(torch.int8).contiguous().clone()
    road_steps = world.road_steps.to(torch.int64).contiguous().clone()
    ego_rank = world.ego_rank.to(torch.int64).contiguous()
    table = NativeTable.of(columns)
    status = load_routed_library().intersection_frames(
        ctypes.byref(road.struct), ctypes.byref(rules.struct), ctypes.byref(table),
        legs.data_ptr(), heads.data_ptr(), yielding.data_ptr(), road_steps.data_ptr(),
        ego_rank.data_ptr(), batch, n, frames, int(world.vehicles.x.dtype == torch.float64),
        threads or torch.get_num_threads(),
    )  # fmt: skip
    if status == 2:
        raise ValueError(f"an ego rank outside the table's {n} rows: {world.ego_rank.tolist()}")
    if status != 0:
        raise ValueError(f"the C++ intersection step refused its input (status {status})")
    return with_columns(world, columns, route_head=heads, yielding=yielding, road_steps=road_steps)
