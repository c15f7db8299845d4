"""The merge-v0 and roundabout-v0 steps in C++ (``routed_native.cpp``): a loop per world.

:func:`routed_step` is :func:`torchrl_grpo.sim.merge.merge_step` or
:func:`torchrl_grpo.sim.roundabout.roundabout_step` with the substeps in C++ (the ego's
and the IDM vehicles' ``act()`` on the road graph, along their routes on the
roundabout, the bicycle model, the closest lane over the road's lanes, every pair's
collision, merge's obstacle); the observation and the reward stay the tensor path's
(:func:`.merge_output.observe_merge`, :func:`.roundabout_output.observe_roundabout`), as
do fresh episodes. Where the tensor path runs each substep as about a thousand
operations on ``[B, K, N]`` tables, the C++ step scans the few vehicles of one world
at a time, on a CPU. The model is the same expression by expression: in float64 it agrees with
the tensor path to rounding (libm and torch round a sine or an arctangent differently,
by an ulp), and it replays its own bits after a restore.

The source compiles on first use (:mod:`.native_build`); worlds are split over
``torch.get_num_threads()`` threads.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import TensorHighwayEnv
    >>> from torchrl_grpo.sim.state import world_from_tensordict
    >>> env = TensorHighwayEnv("merge-v0", num_envs=2, seed=0)
    >>> world = world_from_tensordict(env.reset()["state"])
    >>> after, out = routed_step(world, torch.tensor([1, 3]), env.params)
    >>> after.steps.tolist(), out["observation"].shape
    ([15, 15], torch.Size([2, 5, 5]))
"""

from __future__ import annotations

import ctypes
import functools
from dataclasses import fields
from pathlib import Path

import torch

from torchrl_grpo.sim.intersection_params import IntersectionParams
from torchrl_grpo.sim.lanes import LaneGeometry
from torchrl_grpo.sim.merge_output import observe_merge
from torchrl_grpo.sim.merge_params import MergeParams
from torchrl_grpo.sim.native import (
    MAX_SPEEDS,
    NativeTable,
    with_columns,
    world_columns,
)
from torchrl_grpo.sim.native_build import build_library
from torchrl_grpo.sim.roundabout_output import observe_roundabout
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.state import World

__all__ = ["load_routed_library", "routed_road", "routed_step"]

SOURCE = Path(__file__).with_name("routed_native.cpp")
#: Every file of the C++ step (the library is rebuilt when any changes).
SOURCES = (
    SOURCE,
    *(
        SOURCE.with_name(n)
        for n in (
            "routed_model.h",
            "intersection_rules.h",
            "routed_road.h",
            "highway_native.h",
            "highway_collide.h",
        )
    ),
)
_SCALARS = (
    "frames dt length width max_speed min_speed acc_max comfort_acc_max comfort_acc_min "
    "distance_wanted time_wanted min_acc_gain max_braking_imposed lane_change_delay "
    "kp_a kp_heading kp_lateral max_steering_angle tau_pursuit speed_limit "
    "others_check_collisions n_speeds obstacle_length obstacle_width"
).split()
_TABLES = (
    "geometry lane_id lane_road left right side_left side_right next_lane road_from road_to "
    "road_count road_lanes next_roads"
).split()
_COUNTS = ("lanes", "roads", "width_max", "fanout", "route_length", "obstacle_row")


class RoutedParams(ctypes.Structure):
    """The constants and the road's tables, in ``routed_road.h``'s ``RoutedParams`` order."""

    _fields_ = [(name, ctypes.c_double) for name in _SCALARS]
    _fields_ += [("speeds", ctypes.c_double * MAX_SPEEDS)]
    _fields_ += [(name, ctypes.c_int64) for name in _COUNTS]
    _fields_ += [(name, ctypes.c_void_p) for name in _TABLES]


@functools.cache
def load_routed_library() -> ctypes.CDLL:
    """The compiled step, built on first use (:func:`.native_build.build_library`).

    Raises:
        NativeBuildError: no C++ compiler was found, or it failed (its message is kept).

    Example:
        >>> load_routed_library().routed_step.restype
        <class 'ctypes.c_int'>
    """
    library = build_library(SOURCES)
    library.routed_step.restype = ctypes.c_int
    library.routed_step.argtypes = [
        ctypes.POINTER(RoutedParams), ctypes.POINTER(NativeTable), ctypes.c_void_p,
        ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int, ctypes.c_int, ctypes.c_int,
    ]  # fmt: skip
    library.intersection_frames.restype = ctypes.c_int
    library.intersection_frames.argtypes = [
        ctypes.POINTER(RoutedParams), ctypes.c_void_p, ctypes.POINTER(NativeTable),
        ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
        ctypes.c_int64, ctypes.c_int64, ctypes.c_int, ctypes.c_int, ctypes.c_int,
    ]  # fmt: skip
    return library


class _Road:
    """The structure and the tensors its pointers address (kept alive together)."""

    def __init__(self, params: MergeParams | RoundaboutParams | IntersectionParams) -> None:
        road, car, idm, control = params.road, params.vehicle, params.idm, params.control
        routed = not isinstance(params, MergeParams)
        speeds = control.target_speeds
        if not 1 <= len(speeds) <= MAX_SPEEDS:
            raise ValueError(
                f"the C++ step takes 1 to {MAX_SPEEDS} target speeds, got {len(speeds)}"
            )
        if idm.politeness != 0:
            raise ValueError(f"the C++ routed step has MOBIL's politeness 0, got {idm.politeness}")
        scalars = {
            "frames": params.time.frames, "dt": params.time.dt, "length": car.length,
            "width": car.width, "max_speed": car.max_speed, "min_speed": car.min_speed,
            "acc_max": idm.acc_max, "comfort_acc_max": idm.comfort_acc_max,
            "comfort_acc_min": idm.comfort_acc_min, "distance_wanted": idm.distance_wanted,
            "time_wanted": idm.time_wanted, "min_acc_gain": idm.lane_change_min_acc_gain,
            "max_braking_imposed": idm.lane_change_max_braking_imposed,
            "lane_change_delay": idm.lane_change_delay, "kp_a": control.kp_a,
            "kp_heading": control.kp_heading, "kp_lateral": control.kp_lateral,
            "max_steering_angle": control.max_steering_angle,
            "tau_pursuit": control.tau_pursuit, "speed_limit": road.speed_limit,
            # merge's step tests every pair where either vehicle checks, whatever the flag.
            "others_check_collisions": float(
                params.traffic.others_check_collisions if routed else True
            ),
            "n_speeds": len(speeds),
            "obstacle_length": getattr(params.traffic, "obstacle_length", 0.0),
            "obstacle_width": getattr(params.traffic, "obstacle_width", 0.0),
        }  # fmt: skip
        geo = road.lanes
        columns = [getattr(geo, f.name) for f in fields(LaneGeometry)]
        tables = {
            "lane_id": road.lane_id, "lane_road": road.road, "left": road.left,
            "right": road.right, "side_left": road.side_left, "side_right": road.side_right,
        }  # fmt: skip
        if routed:
            tables.update(
                road_from=road.road_from, road_to=road.road_to, road_lanes=road.road_lanes,
                next_roads=road.next_roads,
                road_count=[sum(k >= 0 for k in row) for row in road.road_lanes],
            )  # fmt: skip
        else:
            tables["next_lane"] = road.next_lane
        self.tensors = {k: torch.tensor(v, dtype=torch.int64) for k, v in tables.items()}
        self.tensors["geometry"] = torch.tensor(
            list(zip(*columns, strict=True)), dtype=torch.float64
        )
        self.tensors = {k: t.contiguous() for k, t in self.tensors.items()}
        counts = {
            "lanes": geo.count, "obstacle_row": params.obstacle_row,
            "roads": road.roads_count if routed else 0,
            "width_max": self.tensors["road_lanes"].shape[1] if routed else 0,
            "fanout": self.tensors["next_roads"].shape[1] if routed else 0,
            "route_length": road.route_length if routed else 0,
        }  # fmt: skip
        self.struct = RoutedParams(
            *(float(scalars[name]) for name in _SCALARS),
            (ctypes.c_double * MAX_SPEEDS)(*speeds),
            *(counts[name] for name in _COUNTS),
            *(self.tensors[k].data_ptr() if k in self.tensors else None for k in _TABLES),
        )


@functools.lru_cache(maxsize=16)
def routed_road(params: MergeParams | RoundaboutParams | IntersectionParams) -> _Road:
    """The constants and road tables the C++ step reads (cached per params).

    Raises:
        ValueError: more target speeds than the C++ step holds, or MOBIL's politeness
            other than 0.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> routed_road(tensor_params("merge-v0")).struct.obstacle_row  # the last of 6 rows
        5
    """
    return _Road(params)


def routed_step(
    world: World,
    action: torch.Tensor,
    params: MergeParams | RoundaboutParams,
    threads: int | None = None,
) -> tuple[World, dict[str, torch.Tensor]]:
    """``env.step(action)`` for B merge or roundabout worlds, the substeps in C++.

    A pure function like :func:`~torchrl_grpo.sim.merge.merge_step` and
    :func:`~torchrl_grpo.sim.roundabout.roundabout_step`: ``world`` is not modified.

    Args:
        world: B worlds on the CPU (the roundabout's with their routes).
        action: ``[B]`` int64 meta-actions.
        params: the scenario's constants (:class:`MergeParams` or :class:`RoundaboutParams`).
        threads: threads over the worlds (default ``torch.get_num_threads()``).

    Returns:
        ``(worlds after the step, their observation with this action's reward)``.

    Raises:
        ValueError: a world off the CPU, or whose routes do not fit the scenario, or
            intersection-v0's params (its frames: :mod:`.intersection_native`).
        NativeBuildError: see :func:`load_routed_library`.

    Example:
        >>> # see the module's example
    """
    if isinstance(params, IntersectionParams):
        raise ValueError(
            "routed_step steps merge-v0 and roundabout-v0; intersection-v0's frames, with "
            "its right of way, are torchrl_grpo.sim.intersection_native.native_frames"
        )
    routed = isinstance(params, RoundaboutParams)
    if routed != (world.route is not None):
        raise ValueError(
            f"the C++ step of {type(params).__name__} needs worlds "
            f"{'with' if routed else 'without'} routes, got "
            f"{'none' if world.route is None else 'routes'}"
        )
    library = load_routed_library()
    batch, n = world.vehicles.x.shape
    columns = world_columns(world, clone=True, routed=True)
    columns["action"] = action.to(torch.int64).contiguous()
    legs = world.route.contiguous() if routed else None
    heads = world.route_head.contiguous().clone() if routed else None
    table = NativeTable.of(columns)
    status = library.routed_step(
        ctypes.byref(routed_road(params).struct), ctypes.byref(table),
        legs.data_ptr() if routed else None, heads.data_ptr() if routed else None,
        batch, n, params.time.frames,
        int(world.vehicles.x.dtype == torch.float64), threads or torch.get_num_threads(),
    )  # fmt: skip
    if status != 0:
        raise ValueError(f"the C++ routed step refused its input (status {status})")
    world = with_columns(world, columns, time=world.time + params.time.step_time, route_head=heads)
    return world, (observe_roundabout if routed else observe_merge)(world, params, action)
