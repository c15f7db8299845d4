"""The highway step in C++ (``highway_native.cpp``): a loop per world, on a CPU.

:func:`native_step` is :func:`torchrl_grpo.sim.simulate.step` for highway-v0 and
highway-fast-v0 on a CPU, with the substeps and the observation in C++: each vehicle
scans its lane's members (sorted per lane once per substep) instead of going through a
batched lane index, and no operation is dispatched per substep, so a step costs about
12 microseconds per world instead of about 6,500 tensor operations per batch;
:func:`native_fresh` draws fresh episodes with the tensor path's bits. The reward stays
the tensor path's. The model is the same expression by expression: in float64 it agrees
with highway-env as the tensor path does (the parity ladder), and in float32 it differs
from the tensor path only where libm and torch round a sine or a power differently. It
replays its own bits after a restore.

The source compiles on first use with the system's C++ compiler (``$CXX``, else
``c++``) into ``$XDG_CACHE_HOME/torchrl_grpo`` (default ``~/.cache/torchrl_grpo``),
once per source version; worlds are split over ``torch.get_num_threads()`` threads.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.rng import seed_keys
    >>> from torchrl_grpo.sim.reset import reset_world
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("highway-fast-v0")
    >>> world = empty_world(8, params.num_vehicles, torch.float64)
    >>> world = reset_world(world._replace(rng_key=seed_keys(torch.arange(8), 0)),
    ...                     torch.ones(8, dtype=torch.bool), params)
    >>> after, out = native_step(world, torch.full((8,), 3), params)
    >>> out["observation"].shape, after.steps.tolist()[:2]
    (torch.Size([8, 5, 5]), [5, 5])
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
from pathlib import Path

import torch

from torchrl_grpo.sim.control import speed_to_index
from torchrl_grpo.sim.native_build import NativeBuildError, build_library
from torchrl_grpo.sim.observation import FEATURES
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.simulate import observe_world
from torchrl_grpo.sim.state import BOOL_FIELDS, FLOAT_FIELDS, INT_FIELDS, World

__all__ = ["NativeBuildError", "load_library", "native_fresh", "native_observe", "native_step"]

logger = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("highway_native.cpp")
#: Every file of the C++ step (the library is rebuilt when any changes).
SOURCES = (
    SOURCE,
    *(SOURCE.with_name(f"highway_{n}.h") for n in ("native", "collide", "observe", "reset")),
)
MAX_SPEEDS = 16
#: The most columns of the observation the C++ step fills.
MAX_FEATURES = 16


class NativeParams(ctypes.Structure):
    """The constants, in ``highway_native.cpp``'s ``Params`` order."""

    _fields_ = [
        (name, ctypes.c_double)
        for name in (
            "lanes_count lane_width lane_length speed_limit margin_length "
            "length width max_speed min_speed "
            "acc_max comfort_acc_max comfort_acc_min distance_wanted time_wanted "
            "politeness min_acc_gain max_braking_imposed lane_change_delay "
            "kp_a kp_heading kp_lateral max_steering_angle "
            "frames dt others_check_collisions n_speeds"
        ).split()
    ]
    _fields_ += [("speeds", ctypes.c_double * MAX_SPEEDS)]
    _fields_ += [
        (name, ctypes.c_double)
        for name in "obs_count obs_features normalize absolute clip see_behind perception".split()
    ]
    _fields_ += [
        (name, ctypes.c_double * MAX_FEATURES) for name in ("feature", "ranged", "low", "high")
    ]
    _fields_ += [
        (name, ctypes.c_double)
        for name in (
            "initial_lane ego_speed ego_index ego_target ego_offset ego_base "
            "speed_lo speed_span spacing_base spacing_per_speed inv_density decay "
            "jitter_lo jitter_span delta_lo delta_span"
        ).split()
    ]


TABLE_COLUMNS = FLOAT_FIELDS + INT_FIELDS + BOOL_FIELDS + ("speed_index", "steps", "action")


class NativeTable(ctypes.Structure):
    """Column pointers, in ``highway_native.cpp``'s ``Table`` order."""

    _fields_ = [(name, ctypes.c_void_p) for name in TABLE_COLUMNS]

    @staticmethod
    def of(columns: dict[str, torch.Tensor]) -> NativeTable:
        """The pointers of ``columns`` (:func:`world_columns`), null where one is absent.

        Example:
            >>> NativeTable.of({}).x is None
            True
        """
        return NativeTable(
            *(columns[name].data_ptr() if name in columns else None for name in TABLE_COLUMNS)
        )


@functools.cache
def load_library() -> ctypes.CDLL:
    """The compiled step, built on first use (see the module's docstring).

    Raises:
        NativeBuildError: no C++ compiler was found, or it failed (its message is kept).

    Example:
        >>> load_library().highway_step.restype
        <class 'ctypes.c_int'>
    """
    library = build_library(SOURCES)
    library.highway_reset.restype = ctypes.c_int
    pointer = ctypes.c_void_p
    library.highway_reset.argtypes = [
        ctypes.POINTER(NativeParams), ctypes.POINTER(NativeTable), ctypes.c_int64,
        ctypes.c_int64, pointer, pointer, pointer, pointer, pointer, pointer, ctypes.c_int,
    ]  # fmt: skip
    library.highway_step.restype = ctypes.c_int
    library.highway_step.argtypes = [
        ctypes.POINTER(NativeParams),
        ctypes.POINTER(NativeTable),
        ctypes.c_int64,
        ctypes.c_int64,
        ctypes.c_int,
        ctypes.c_void_p,
        ctypes.c_int,
        ctypes.c_int,
    ]
    return library


@functools.lru_cache(maxsize=32)
def native_params(params: HighwayParams) -> NativeParams:
    """The C++ step's constants for ``params`` (cached).

    Raises:
        ValueError: a config the C++ step cannot hold, such as more than 16 target speeds.
    """
    speeds = params.control.target_speeds
    if not 1 <= len(speeds) <= MAX_SPEEDS:
        raise ValueError(f"the C++ step takes 1 to {MAX_SPEEDS} target speeds, got {len(speeds)}")
    road, car, idm, control = params.road, params.vehicle, params.idm, params.control
    values = NativeParams(
        road.lanes_count, road.lane_width, road.lane_length, road.speed_limit,
        road.margin_length, car.length, car.width, car.max_speed, car.min_speed,
        idm.acc_max, idm.comfort_acc_max, idm.comfort_acc_min, idm.distance_wanted,
        idm.time_wanted, idm.politeness, idm.lane_change_min_acc_gain,
        idm.lane_change_max_braking_imposed, idm.lane_change_delay,
        control.kp_a, control.kp_heading, control.kp_lateral, control.max_steering_angle,
        params.time.frames, params.time.dt, float(params.traffic.others_check_collisions),
        len(speeds),
    )  # fmt: skip
    for k, speed in enumerate(speeds):
        values.speeds[k] = speed
    obs = params.observation
    if len(obs.features) > MAX_FEATURES:
        raise ValueError(
            f"the C++ step fills 1 to {MAX_FEATURES} features, got {len(obs.features)}"
        )
    values.obs_count, values.obs_features = obs.vehicles_count, len(obs.features)
    values.normalize, values.absolute, values.clip = obs.normalize, obs.absolute, obs.clip
    values.see_behind, values.perception = obs.see_behind, obs.perception_distance
    ranges = dict(obs.features_range)
    for k, name in enumerate(obs.features):
        values.feature[k] = FEATURES.index(name)
        if name in ranges:
            values.ranged[k] = 1
            values.low[k], values.high[k] = ranges[name]
    _fresh_constants(values, params)
    return values


def _fresh_constants(values: NativeParams, params: HighwayParams) -> None:
    """reset.py's constants, each computed by the same Python expression as there."""
    t, limit = params.traffic, params.road.speed_limit
    values.initial_lane = -1 if t.initial_lane_id is None else int(t.initial_lane_id)
    ego = torch.tensor([t.ego_speed], dtype=torch.float64)
    index = int(speed_to_index(ego, params.control.target_speeds)[0])
    values.ego_speed, values.ego_index = t.ego_speed, index
    table = torch.tensor(params.control.target_speeds, dtype=torch.float64)
    values.ego_target = float(table[index])
    values.decay = math.exp(-t.spacing_decay * params.road.lanes_count)
    values.ego_offset = t.ego_spacing * (t.spacing_base + t.spacing_per_speed * t.ego_speed)
    values.ego_offset *= values.decay
    values.ego_base = t.first_offsets * values.ego_offset
    values.speed_lo = t.speed_low * limit
    values.speed_span = t.speed_high * limit - values.speed_lo
    values.spacing_base, values.spacing_per_speed = t.spacing_base, t.spacing_per_speed
    values.inv_density = 1 / t.vehicles_density
    values.jitter_lo, values.jitter_span = t.jitter[0], t.jitter[1] - t.jitter[0]
    low, high = params.idm.delta_range
    values.delta_lo, values.delta_span = low, high - low


def world_columns(world: World, clone: bool, routed: bool = False) -> dict[str, torch.Tensor]:
    """The contiguous columns the C++ code reads (and, cloned, writes), by ``Table`` name.

    Raises:
        ValueError: a world off the CPU, or with routes where ``routed`` is False (not a
            highway scenario).
    """
    if world.vehicles.x.device.type != "cpu":
        raise ValueError(f"the C++ step runs on the CPU; the world is on {world.vehicles.x.device}")
    if world.route is not None and not routed:
        raise ValueError("the C++ step covers highway-v0 and highway-fast-v0 (no routes)")
    columns = {name: getattr(world.vehicles, name) for name in world.vehicles._fields}
    columns.update(speed_index=world.speed_index, steps=world.steps)
    # Cloned: the C++ code writes into them and the input world stays as it was.
    return {k: t.contiguous().clone() if clone else t.contiguous() for k, t in columns.items()}


def with_columns(world: World, columns: dict[str, torch.Tensor], **words) -> World:
    """``world`` holding the columns the C++ code wrote, and the given per-world words."""
    vehicles = world.vehicles._replace(**{k: columns[k] for k in world.vehicles._fields})
    return world._replace(
        vehicles=vehicles, speed_index=columns["speed_index"], steps=columns["steps"], **words
    )


def _run(world: World, action: torch.Tensor | None, params: HighwayParams, threads, frames):
    """The C++ call: ``frames`` substeps of a copy of ``world``, then its observation."""
    library = load_library()
    v = world.vehicles
    batch, n = v.x.shape
    copy = frames > 0  # an observation alone writes nothing
    columns = world_columns(world, clone=copy)
    if copy:
        columns["action"] = action.to(torch.int64).contiguous()
    obs = params.observation
    observation = v.x.new_empty(batch, obs.vehicles_count, len(obs.features))
    table = NativeTable.of(columns)
    status = library.highway_step(
        ctypes.byref(native_params(params)), ctypes.byref(table), batch, n, frames,
        observation.data_ptr(), int(v.x.dtype == torch.float64),
        threads or torch.get_num_threads(),
    )  # fmt: skip
    if status != 0:
        raise ValueError(f"the C++ step refused its input (status {status})")
    if copy:
        world = with_columns(world, columns, time=world.time + params.time.step_time)
    return world, observe_world(world, params, observation=observation)


def native_step(
    world: World, action: torch.Tensor, params: HighwayParams, threads: int | None = None
) -> tuple[World, dict[str, torch.Tensor]]:
    """``env.step(action)`` for B highway worlds, the substeps and the observation in C++.

    A pure function like :func:`~torchrl_grpo.sim.simulate.step`: ``world`` is not
    modified.

    Args:
        world: B worlds on the CPU (highway-v0 or highway-fast-v0; no routes).
        action: ``[B]`` int64 meta-actions (-1: none).
        params: the constants.
        threads: threads over the worlds (default ``torch.get_num_threads()``).

    Returns:
        ``(worlds after the step, observe_world of them)``.

    Raises:
        ValueError: a world off the CPU, or with routes (not a highway scenario).
        NativeBuildError: see :func:`load_library`.

    Example:
        >>> # see the module's example
    """
    return _run(world, action, params, threads, params.time.frames)


def native_observe(
    world: World, params: HighwayParams, threads: int | None = None
) -> dict[str, torch.Tensor]:
    """:func:`~torchrl_grpo.sim.simulate.observe_world` with the observation in C++.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> from torchrl_grpo.sim.state import empty_world
        >>> params = tensor_params("highway-fast-v0")
        >>> native_observe(empty_world(2, 21), params)["observation"].shape
        torch.Size([2, 5, 5])
    """
    return _run(world, None, params, threads, 0)[1]


def native_fresh(
    world: World,
    rows: torch.Tensor,
    words: torch.Tensor,
    seeds: torch.Tensor,
    params: HighwayParams,
) -> tuple[World, torch.Tensor, torch.Tensor]:
    """Fresh episodes in ``rows``, drawn in C++ with the tensor path's bits.

    What :func:`~torchrl_grpo.sim.reset.reset_world` and the env's highway-env generator
    words (``fresh_highway_words``) give, from the same streams: a reset row holds the
    same values either way (tested bit for bit).

    Args:
        world: B worlds on the CPU.
        rows: ``[B]`` bool, the rows to reset.
        words: ``[B, 10]`` int64, the highway-env generator words the bridge carries.
        seeds: ``[B]`` int64, the seed each row was reset with (-1: drawn).
        params: the constants.

    Returns:
        ``(world, words, seeds)`` with the rows reset (new tensors; the inputs are kept).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> from torchrl_grpo.sim.rng import seed_keys
        >>> from torchrl_grpo.sim.state import empty_world
        >>> params = tensor_params("highway-fast-v0")
        >>> world = empty_world(2, 21)._replace(rng_key=seed_keys(torch.arange(2), 0))
        >>> words = torch.zeros(2, 10, dtype=torch.int64)
        >>> world, words, seeds = native_fresh(world, torch.tensor([True, False]), words,
        ...                                    torch.zeros(2, dtype=torch.int64), params)
        >>> world.rng_counter.tolist(), seeds.tolist()
        ([2, 0], [-1, 0])
    """
    v = world.vehicles
    batch, n = v.x.shape
    columns = world_columns(world, clone=True)
    key, counter = world.rng_key.contiguous(), world.rng_counter.contiguous().clone()
    time = world.time.contiguous().clone()
    words, seeds = words.contiguous().clone(), seeds.contiguous().clone()
    rows = rows.to(torch.bool).contiguous()
    table = NativeTable.of(columns)
    status = load_library().highway_reset(
        ctypes.byref(native_params(params)), ctypes.byref(table), batch, n,
        *(t.data_ptr() for t in (rows, key, counter, time, words, seeds)),
        int(v.x.dtype == torch.float64),
    )  # fmt: skip
    if status != 0:
        raise ValueError(f"the C++ reset refused its input (status {status})")
    return with_columns(world, columns, time=time, rng_counter=counter), words, seeds
