"""The state of a TensorHighwayEnv: its layout, its checks, reseeding and row selection.

A tensor state is :func:`~torchrl_grpo.sim.world_to_tensordict`'s TensorDict ``[B]`` of
a world, plus what the env adds: ``highway`` (highway-env's generator words and reset
seed, carried for the bridge) and ``fingerprint`` (a hash of the scenario, config and
dtype, so that a state of another config is refused by name).

Example:
    >>> from torchrl_grpo.envs import TensorHighwayEnv
    >>> env = TensorHighwayEnv(num_envs=2, seed=0)
    >>> state = env.get_state()
    >>> check_state_structure(state, env.state_spec["state"], env.fingerprint)
    >>> check_state_values(state, env.params)
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.core.errors import StateCorruptedError, StateMismatchError
from torchrl_grpo.envs.core.gym_state import RNG_WORDS, invalid_rng_rows, seeded_rng_words
from torchrl_grpo.envs.highway.schema import MAX_MAGNITUDE
from torchrl_grpo.sim.intersection_reset import check_regulated
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.rng import mix64, uniform
from torchrl_grpo.sim.state import (
    BOOL_FIELDS,
    FLOAT_FIELDS,
    INT_FIELDS,
    World,
    check_world,
    map_world,
    world_from_tensordict,
)

__all__ = [
    "check_state_structure",
    "check_state_values",
    "fresh_highway_words",
    "reseeded",
    "tensor_state_spec",
    "where_rows",
]


def tensor_state_spec(
    batch: torch.Size,
    num_vehicles: int,
    dtype: torch.dtype,
    device: torch.device,
    route_length: int = 0,
    regulated: bool = False,
) -> Composite:
    """The spec of a tensor state ``[B]`` of worlds of ``num_vehicles`` vehicles.

    With ``route_length`` R > 0 (roundabout-v0, intersection-v0) it holds each
    vehicle's route too: ``route.legs`` ``[B, N, R]`` and ``route.head`` ``[B, N]``;
    ``regulated`` (intersection-v0) adds ``yielding`` ``[B, N]`` int8, ``road_steps``
    and ``ego_rank`` ``[B]``.

    Example:
        >>> spec = tensor_state_spec(torch.Size([4]), 21, torch.float32, torch.device("cpu"))
        >>> spec["vehicles", "x"].shape, spec["time"].dtype
        (torch.Size([4, 21]), torch.float64)
    """
    b, n = batch, num_vehicles

    def u(shape: tuple[int, ...], kind: torch.dtype) -> Unbounded:
        return Unbounded(shape, dtype=kind, device=device)

    table = {k: u((*b, n), dtype) for k in FLOAT_FIELDS}
    table |= {k: u((*b, n), torch.int64) for k in INT_FIELDS}
    table |= {k: u((*b, n), torch.bool) for k in BOOL_FIELDS}
    words = u(b, torch.int64)
    highway = Composite(
        rng=u((*b, RNG_WORDS), torch.int64), seed=words.clone(), shape=b, device=device
    )
    spec = Composite(
        vehicles=Composite(table, shape=(*b, n), device=device),
        speed_index=words.clone(),
        time=u(b, torch.float64),
        steps=words.clone(),
        rng=Composite(key=words.clone(), counter=words.clone(), shape=b, device=device),
        highway=highway,
        fingerprint=words.clone(),
        shape=b,
        device=device,
    )
    if route_length:
        legs, head = u((*b, n, route_length), torch.int64), u((*b, n), torch.int64)
        spec["route"] = Composite(legs=legs, head=head, shape=(*b, n), device=device)
    if regulated:
        spec["yielding"] = u((*b, n), torch.int8)
        spec["road_steps"], spec["ego_rank"] = words.clone(), words.clone()
    return spec


def check_state_structure(state: TensorDictBase, spec: Composite, fingerprint: int) -> None:
    """Keys, shapes (any batch ``[M]``), dtypes and device against ``spec``; then the fingerprint.

    Raises:
        StateCorruptedError: a missing entry, or one of the wrong shape, dtype or device.
        StateMismatchError: a state of another scenario, config or dtype.

    Example:
        >>> from torchrl_grpo.envs import StateCorruptedError, TensorHighwayEnv
        >>> env = TensorHighwayEnv(num_envs=2)
        >>> try:
        ...     check_state_structure(env.get_state().exclude("time"), env.state_spec["state"],
        ...                           env.fingerprint)
        ... except StateCorruptedError as err:
        ...     print(err)
        the state is truncated: it has no 'time' entry
    """
    if not isinstance(state, TensorDictBase):
        raise StateCorruptedError(f"a state must be a TensorDict, got {type(state).__name__}")
    if state.batch_dims != 1:
        raise StateCorruptedError(f"states must have batch size [M], got {tuple(state.batch_size)}")
    keys = set(state.keys(True, True))
    for key in spec.keys(True, True):
        name = ".".join(key) if isinstance(key, tuple) else key
        if key not in keys:
            raise StateCorruptedError(f"the state is truncated: it has no {name!r} entry")
        value, leaf = state.get(key), spec[key]
        shape = (*state.batch_size, *leaf.shape[1:])
        if not isinstance(value, torch.Tensor):
            raise StateCorruptedError(f"state entry {name!r} is a {type(value).__name__}")
        if value.shape != shape or value.dtype != leaf.dtype:
            raise StateCorruptedError(
                f"state entry {name!r}: expected {tuple(shape)} {leaf.dtype}, "
                f"got {tuple(value.shape)} {value.dtype}"
            )
        if value.device != leaf.device:
            raise StateCorruptedError(
                f"state entry {name!r} is on {value.device}, the env on {leaf.device}"
            )
    if not bool((state.get("fingerprint") == fingerprint).all()):
        raise StateMismatchError(
            "the state belongs to another scenario, config or dtype than this TensorHighwayEnv"
        )


def check_state_values(state: TensorDictBase, params: HighwayParams) -> None:
    """Every entry's values: the world's (:func:`~torchrl_grpo.sim.check_world`) and the words.

    Floats (and the clock) must be finite and within :data:`~.schema.MAX_MAGNITUDE`,
    the bound HighwayEnv's codec holds every float of a highway-env state to.

    Raises:
        StateCorruptedError: naming each entry that does not fit, its rows and (for
            floats) their values.

    Example:
        >>> from torchrl_grpo.envs import StateCorruptedError, TensorHighwayEnv
        >>> env = TensorHighwayEnv(num_envs=2)
        >>> state = env.get_state()
        >>> _ = state["highway", "rng"].zero_()  # an invalid PCG64 state (even increment)
        >>> try:
        ...     check_state_values(state, env.params)
        ... except StateCorruptedError as err:
        ...     print(err)
        invalid state: highway.rng: not a valid PCG64 state in rows [0, 1]
    """
    world = world_from_tensordict(state)
    problems = check_world(world, params, MAX_MAGNITUDE)
    if world.yielding is not None:
        problems += check_regulated(world)
    words = state.get(("highway", "rng"))
    bad = invalid_rng_rows(words)
    if bool(bad.any()):
        rows = bad.nonzero().flatten()[:8].tolist()
        problems.append(f"highway.rng: not a valid PCG64 state in rows {rows}")
    if problems:
        raise StateCorruptedError("invalid state: " + "; ".join(problems))


def where_rows(rows: torch.Tensor, new: World, old: World) -> World:
    """``new`` where ``rows`` (``[B]``) is set, ``old`` elsewhere.

    Example:
        >>> from torchrl_grpo.sim import empty_world
        >>> a, b = empty_world(2, 3), empty_world(2, 3)
        >>> b.vehicles.x.fill_(1.0)
        tensor(...)
        >>> where_rows(torch.tensor([True, False]), b, a).vehicles.x[:, 0].tolist()
        [1.0, 0.0]
    """
    return map_world(
        lambda a, b: torch.where(rows.reshape(-1, *([1] * (a.ndim - 1))), a, b), new, old
    )


def fresh_highway_words(world: World, rows: torch.Tensor) -> tuple[World, torch.Tensor]:
    """Valid highway-env generator words for freshly drawn worlds, from their own streams.

    A PCG64 state is any 128-bit state with an odd 128-bit increment: the words are
    drawn from each world's stream (its counter advances on ``rows``), never all zero.

    Returns:
        ``(world with the advanced counters, [B, RNG_WORDS] int64 words)``.

    Example:
        >>> from torchrl_grpo.sim import empty_world, seed_keys
        >>> w = empty_world(2, 3)._replace(rng_key=seed_keys(torch.arange(2), 0))
        >>> w2, words = fresh_highway_words(w, torch.tensor([True, False]))
        >>> bool(words[:, 4].remainder(2).eq(1).all()), w2.rng_counter.tolist()
        (True, [1, 0])
    """
    u, counter = uniform(world.rng_key, world.rng_counter, 8)
    words = (u * (1 << 32)).to(torch.int64)
    words[:, 4] |= 1
    words = torch.cat([words, torch.zeros_like(words[:, :2])], dim=1)
    counter = torch.where(rows, counter, world.rng_counter)
    return world._replace(rng_counter=counter), words


def reseeded(state: TensorDictBase, seeds: Sequence[int]) -> TensorDict:
    """A copy of ``state`` ``[M]`` whose random streams restart from ``seeds`` (one per row).

    Both streams: the simulator's own (the row's next fresh episode) and the highway-env
    generator words the bridge carries (as ``reset(seed=seed)`` installs them).

    Example:
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> state = TensorHighwayEnv(num_envs=2).get_state()
        >>> reseeded(state, [5, 5])["rng", "key"].unique().numel()
        1
    """
    out = state.clone()
    values = torch.tensor(list(seeds), dtype=torch.int64, device=state.device)
    out.set(("rng", "key"), mix64(mix64(values) + 1))
    out.set(("rng", "counter"), torch.zeros_like(values))
    out.set(("highway", "rng"), torch.stack([seeded_rng_words(s) for s in seeds]).to(state.device))
    out.set(("highway", "seed"), values)
    return out
