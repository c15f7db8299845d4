"""The state of B highway worlds: a vehicle table ``[B, N]`` and a few per-world words.

Row 0 of the vehicle table is the ego (highway-env's ``MDPVehicle``); rows ``1..N-1``
are the other vehicles (``IDMVehicle``) in ``road.vehicles`` order, which is the order
in which highway-env lets them act and checks their collisions. The state is
complete: the next step depends on nothing else, so a snapshot is a clone and G
branches are G copies along the batch dimension.

The step functions work on :class:`World`, a named tuple of plain tensors (cheap to
build, and friendly to ``torch.compile``); :func:`world_to_tensordict` and
:func:`world_from_tensordict` convert at the env's boundary.

Example:
    >>> import torch
    >>> world = empty_world(batch=2, num_vehicles=3, dtype=torch.float32)
    >>> td = world_to_tensordict(world)
    >>> td["vehicles"].batch_size, td["vehicles", "speed"].dtype
    (torch.Size([2, 3]), torch.float32)
    >>> back = world_from_tensordict(td)
    >>> torch.equal(back.vehicles.x, world.vehicles.x)
    True
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_grpo.sim.params import HighwayParams

__all__ = [
    "BOOL_FIELDS",
    "FLOAT_FIELDS",
    "INT_FIELDS",
    "Vehicles",
    "World",
    "check_world",
    "empty_world",
    "map_world",
    "take",
    "world_from_tensordict",
    "world_to_tensordict",
]


class Vehicles(NamedTuple):
    """The vehicle table, every field ``[B, N]``; row 0 is the ego.

    Fields (a named tuple's, so listed here rather than as attributes):
        x: longitudinal position (m).
        y: lateral position (m); lane ``i`` is centred on ``y = i * lane_width``.
        heading: heading (rad), not wrapped.
        speed: speed (m/s), can be negative.
        target_speed: the speed controller's set-point (m/s).
        steering: the last substep's steering command (rad), after clipping.
        acceleration: the last substep's acceleration command (m/s^2), after clipping.
        timer: seconds since the last MOBIL decision (other vehicles only).
        delta: IDM velocity exponent (other vehicles only; drawn at reset).
        impact_x: pending displacement from a predicted collision, applied next substep.
        impact_y: see ``impact_x``.
        lane: the closest lane, updated after every substep.
        target_lane: the lane the steering controller follows.
        crashed: the vehicle has collided.
        impact: whether ``impact_x, impact_y`` is pending (highway-env's ``impact is not None``).
        check_collisions: whether the vehicle checks its own collisions.
        present: the row holds a vehicle (padding rows are ignored everywhere).

    Example:
        >>> v = empty_world(2, 3).vehicles
        >>> v.speed.shape, v.lane.dtype, v.present.all().item()
        (torch.Size([2, 3]), torch.int64, True)
    """

    x: torch.Tensor
    y: torch.Tensor
    heading: torch.Tensor
    speed: torch.Tensor
    target_speed: torch.Tensor
    steering: torch.Tensor
    acceleration: torch.Tensor
    timer: torch.Tensor
    delta: torch.Tensor
    impact_x: torch.Tensor
    impact_y: torch.Tensor
    lane: torch.Tensor
    target_lane: torch.Tensor
    crashed: torch.Tensor
    impact: torch.Tensor
    check_collisions: torch.Tensor
    present: torch.Tensor


#: Float columns of :class:`Vehicles` (the env's dtype).
FLOAT_FIELDS = (
    "x",
    "y",
    "heading",
    "speed",
    "target_speed",
    "steering",
    "acceleration",
    "timer",
    "delta",
    "impact_x",
    "impact_y",
)
#: Integer (int64) columns of :class:`Vehicles`.
INT_FIELDS = ("lane", "target_lane")
#: Boolean columns of :class:`Vehicles`.
BOOL_FIELDS = ("crashed", "impact", "check_collisions", "present")


class World(NamedTuple):
    """B worlds.

    Fields (a named tuple's, so listed here rather than as attributes):
        vehicles: the ``[B, N]`` vehicle table.
        speed_index: ``[B]`` int64, the ego's index into the target speeds.
        time: ``[B]`` float64 seconds since reset (highway-env's ``env.time``).
        steps: ``[B]`` int64 substeps since reset (highway-env's ``env.steps``).
        rng_key: ``[B]`` int64 key of the world's random stream (see :mod:`.rng`).
        rng_counter: ``[B]`` int64 counter of that stream.
        route: ``[B, N, R]`` int64 route legs (codes of :mod:`.routes`; roundabout-v0 only).
        route_head: ``[B, N]`` int64, each route's first leg not yet dropped (or ``None``).
        yielding: ``[B, N]`` int8 yield states (intersection-v0 only, :mod:`.regulation`).
        road_steps: ``[B]`` int64 frames the road has run, the reset's included (``road.steps``).
        ego_rank: ``[B]`` int64, the ego's place in ``road.vehicles`` (vehicles before it).

    Example:
        >>> world = empty_world(4, 21)
        >>> world.time.dtype, world.vehicles.x.shape
        (torch.float64, torch.Size([4, 21]))
    """

    vehicles: Vehicles
    speed_index: torch.Tensor
    time: torch.Tensor
    steps: torch.Tensor
    rng_key: torch.Tensor
    rng_counter: torch.Tensor
    route: torch.Tensor | None = None
    route_head: torch.Tensor | None = None
    yielding: torch.Tensor | None = None
    road_steps: torch.Tensor | None = None
    ego_rank: torch.Tensor | None = None


def map_world(fn, *worlds: World) -> World:
    """``fn`` of the corresponding tensors of ``worlds``, as a world (absent fields stay ``None``).

    Example:
        >>> w = map_world(lambda t: t[:1], empty_world(3, 2))
        >>> w.vehicles.x.shape, w.steps.shape
        (torch.Size([1, 2]), torch.Size([1]))
    """

    def apply(*parts):
        if parts[0] is None or isinstance(parts[0], torch.Tensor):
            return None if parts[0] is None else fn(*parts)
        return type(parts[0])(*(apply(*column) for column in zip(*parts, strict=True)))

    return apply(*worlds)


def take(table: torch.Tensor, at: torch.Tensor) -> torch.Tensor:
    """Entries of a ``[B, N]`` table at flat indices ``row * N + column``.

    ``index_select`` on the flattened table: several times faster than advanced
    indexing (``table[rows, columns]``) on CPU, and the same values.

    Example:
        >>> take(torch.tensor([[1, 2], [3, 4]]), torch.tensor([3, 0])).tolist()
        [4, 1]
    """
    return table.reshape(-1).index_select(0, at)


def empty_world(
    batch: int,
    num_vehicles: int,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    route_length: int = 0,
    regulated: bool = False,
) -> World:
    """A world of zeros with every row present: a template for specs and tests.

    Args:
        batch: B.
        num_vehicles: N, the ego included.
        dtype: the float dtype of the vehicle table.
        device: where the tensors live.
        route_length: R, the legs a route holds (0: no routes, as on the highway).
        regulated: with the intersection's ``yielding``, ``road_steps`` and ``ego_rank``.

    Returns:
        A :class:`World`.

    Example:
        >>> empty_world(4, 21).vehicles.x.shape
        torch.Size([4, 21])
    """
    shape = (batch, num_vehicles)
    floats = {k: torch.zeros(shape, dtype=dtype, device=device) for k in FLOAT_FIELDS}
    ints = {k: torch.zeros(shape, dtype=torch.int64, device=device) for k in INT_FIELDS}
    flags = {k: torch.zeros(shape, dtype=torch.bool, device=device) for k in BOOL_FIELDS}
    flags["present"] = torch.ones(shape, dtype=torch.bool, device=device)
    words = torch.zeros(batch, dtype=torch.int64, device=device)
    route = head = None
    if route_length:
        route = torch.full((*shape, route_length), -1, dtype=torch.int64, device=device)
        head = torch.zeros(shape, dtype=torch.int64, device=device)
    return World(
        vehicles=Vehicles(**floats, **ints, **flags),
        speed_index=words.clone(),
        time=torch.zeros(batch, dtype=torch.float64, device=device),
        steps=words.clone(),
        rng_key=words.clone(),
        rng_counter=words.clone(),
        route=route,
        route_head=head,
        yielding=torch.zeros(shape, dtype=torch.int8, device=device) if regulated else None,
        road_steps=words.clone() if regulated else None,
        ego_rank=words.clone() if regulated else None,
    )


def world_to_tensordict(world: World) -> TensorDict:
    """The world as a TensorDict ``[B]`` (the env's ``state`` entry).

    Args:
        world: B worlds.

    Returns:
        ``TensorDict(vehicles=[B, N] table, speed_index, time, steps, rng={key, counter})``.

    Example:
        >>> sorted(world_to_tensordict(empty_world(1, 2)).keys())
        ['rng', 'speed_index', 'steps', 'time', 'vehicles']
    """
    v = world.vehicles
    batch = v.x.shape[:1]
    td = TensorDict(
        {
            "vehicles": TensorDict(v._asdict(), batch_size=v.x.shape[:2]),
            "speed_index": world.speed_index,
            "time": world.time,
            "steps": world.steps,
            "rng": TensorDict(key=world.rng_key, counter=world.rng_counter, batch_size=batch),
        },
        batch_size=batch,
    )
    if world.route is not None:
        route = TensorDict(legs=world.route, head=world.route_head, batch_size=v.x.shape[:2])
        td.set("route", route)
    if world.yielding is not None:
        td.set("yielding", world.yielding)
        td.set("road_steps", world.road_steps)
        td.set("ego_rank", world.ego_rank)
    return td


def world_from_tensordict(state: TensorDictBase) -> World:
    """The :class:`World` a state TensorDict holds (no copy).

    Args:
        state: a TensorDict laid out as :func:`world_to_tensordict` writes it.

    Returns:
        A :class:`World` of the same tensors.

    Example:
        >>> world_from_tensordict(world_to_tensordict(empty_world(1, 2))).steps.tolist()
        [0]
    """
    table = state.get("vehicles")
    route = state.get("route", None)
    return World(
        vehicles=Vehicles(**{k: table.get(k) for k in Vehicles._fields}),
        speed_index=state.get("speed_index"),
        time=state.get("time"),
        steps=state.get("steps"),
        rng_key=state.get(("rng", "key")),
        rng_counter=state.get(("rng", "counter")),
        route=None if route is None else route.get("legs"),
        route_head=None if route is None else route.get("head"),
        yielding=state.get("yielding", None),
        road_steps=state.get("road_steps", None),
        ego_rank=state.get("ego_rank", None),
    )


def check_world(
    world: World, params: HighwayParams, max_magnitude: float = float("inf")
) -> list[str]:
    """The problems that make ``world`` unfit for ``params``, each naming its entry.

    Checks every entry: float columns finite and within ``max_magnitude``, lanes and
    the speed index in range, counters non-negative, the ego present and checking
    collisions, the others' collision checks as the scenario sets them (the collision
    pass relies on it). Values that highway-env itself reaches (negative speeds,
    unwrapped headings, speeds past the clip) are admitted.

    Args:
        world: B worlds.
        params: the scenario they must belong to.
        max_magnitude: the largest magnitude a float (and the clock) may hold; the
            envs pass the bound of highway-env's state codec.

    Returns:
        Messages such as ``"vehicles.speed: not finite in rows [3] (values [nan])"``;
        empty if fit.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> params = tensor_params("highway-fast-v0")
        >>> w = empty_world(2, params.num_vehicles, dtype=torch.float64)
        >>> w.vehicles.check_collisions[:, 0] = True
        >>> w.vehicles.speed[1, 3] = float("nan")
        >>> check_world(w, params)
        ['vehicles.speed: not finite in rows [1] (values [nan])']
        >>> w.vehicles.speed[1, 3] = -1e6
        >>> check_world(w, params, max_magnitude=1e5)
        ['vehicles.speed: not finite, or beyond 100000 in rows [1] (values [-1000000.0])']
    """
    v = world.vehicles
    problems: list[str] = []

    def bad(name: str, mask: torch.Tensor) -> None:
        if mask.ndim > 1:
            mask = mask.flatten(1).any(-1)
        if bool(mask.any()):
            rows = mask.nonzero().flatten()[:8].tolist()
            problems.append(f"{name}: {_WHY[name.split('.')[-1]]} in rows {rows}")

    def beyond(name: str, ok: torch.Tensor, values: torch.Tensor, why: str) -> None:
        # Reduced to rows before the one host read: as cheap as the isfinite it replaced.
        rows_ok = ok.all(-1) if ok.ndim > 1 else ok
        if not bool(rows_ok.all()):
            rows = (~rows_ok).nonzero().flatten()[:8]
            # Per offending row, its first offending value.
            if ok.ndim > 1:
                first = (~ok[rows]).to(torch.int8).argmax(-1)
                shown = values[rows, first]
            else:
                shown = values[rows]
            problems.append(f"{name}: {why} in rows {rows.tolist()} (values {shown.tolist()})")

    n = params.num_vehicles
    if v.x.ndim != 2 or v.x.shape[1] != n:
        return [
            f"vehicles: expected [B, {n}] rows (the ego and {n - 1} others), got {tuple(v.x.shape)}"
        ]
    finite = max_magnitude == float("inf")
    why = "not finite" if finite else f"not finite, or beyond {max_magnitude:g}"
    # The largest finite value of the dtype when unbounded: inf and NaN fail ``<=``.
    limit = min(max_magnitude, torch.finfo(v.x.dtype).max)
    for name in FLOAT_FIELDS:
        column = getattr(v, name)
        beyond(f"vehicles.{name}", column.abs() <= limit, column, why)
    lanes = params.road.lanes_count
    bad("vehicles.lane", (v.lane < 0) | (v.lane >= lanes))
    bad("vehicles.target_lane", (v.target_lane < 0) | (v.target_lane >= lanes))
    bad("vehicles.present", ~v.present[:, :1])
    others = params.traffic.others_check_collisions
    expected = torch.full_like(v.check_collisions, others)
    expected[:, 0] = True
    bad("vehicles.check_collisions", (v.check_collisions != expected) & v.present)
    speeds = len(params.control.target_speeds)
    bad("speed_index", (world.speed_index < 0) | (world.speed_index >= speeds))
    time_limit = min(max_magnitude, torch.finfo(world.time.dtype).max)
    clock = (world.time >= 0) & (world.time <= time_limit)
    beyond("time", clock, world.time, "negative, " + why)
    bad("steps", world.steps < 0)
    bad("rng.counter", world.rng_counter < 0)
    codes = getattr(params.road, "route_codes", 0)
    if codes and world.route is not None:
        bad("route.legs", (world.route < -1) | (world.route >= codes))
        length = world.route.shape[-1]
        bad("route.head", (world.route_head < 0) | (world.route_head > length))
    return problems


_WHY = {
    "lane": "outside the road's lanes",
    "target_lane": "outside the road's lanes",
    "present": "the ego (row 0) is missing",
    "check_collisions": "collision checks differ from the scenario's (ego: True, others: "
    "True in highway-v0, False in highway-fast-v0)",
    "speed_index": "outside the target speeds",
    "steps": "negative",
    "counter": "negative",
    "legs": "outside the road's lanes and roads",
    "head": "outside the route",
}
