"""Road objects from a highway-env state's entity tables: checked, then rebuilt.

The codec's restore builds every object of a state first and writes nothing into the
env until all of them are valid: :func:`decode_entities` checks each slot (kind, class,
fields, finite positions, references) and :func:`rebuild_derived` reattaches what the
tables do not store.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from highway_env.vehicle.dynamics import BicycleVehicle
from highway_env.vehicle.kinematics import Vehicle

from torchrl_grpo.envs.core.errors import StateCorruptedError
from torchrl_grpo.envs.highway.layout import KIND, VEHICLE
from torchrl_grpo.envs.highway.layout_decode import EntityDecoder

__all__ = ["decode_entities", "rebuild_derived"]


def decode_entities(
    decoder: EntityDecoder,
    classes: list[type],
    core: Any,
    blocks: dict[str, np.ndarray],
    max_vehicles: int,
    history_sizes: dict[type, int | None],
) -> tuple[list, list, dict]:
    """Check every entity slot and build the road objects it holds (nothing written).

    Args:
        decoder: the codec's entity decoder.
        classes: the class registry (class ids index it).
        core: the unwrapped env the objects are built for.
        blocks: the entity tables as numpy arrays (``f64`` viewed as float64).
        max_vehicles: slots ``[0, max_vehicles)`` hold vehicles, the rest objects.
        history_sizes: a cache of each class's ``HISTORY_SIZE``, filled as classes appear.

    Returns:
        ``(vehicles, objects, {slot: object})``.

    Raises:
        StateCorruptedError: a slot of the wrong kind, a non-finite position, a
            reference to an empty slot, an object that cannot be rebuilt.

    Example:
        >>> import gymnasium as gym
        >>> from torchrl_grpo.envs.highway.highway_codec import HighwayStateCodec
        >>> env = gym.make("merge-v0")
        >>> _ = env.reset(seed=0)
        >>> codec = HighwayStateCodec()
        >>> codec.bind(env)
        >>> state = codec.encode(env)
        >>> blocks = {b: state["entities", b].numpy() for b in codec.layout.widths}
        >>> blocks["f64"] = blocks["f64"].view(np.float64)
        >>> vehicles, objects, _ = decode_entities(
        ...     codec.decoder, codec.classes, env.unwrapped, blocks, codec.max_vehicles, {})
        >>> len(vehicles), len(objects)
        (5, 1)
    """
    # Checks every slot (kind, class, required fields, values) before building lists.
    decoded = decoder.decode(blocks, classes)
    by_slot = {slot: obj for slot, _, obj, _ in decoded}
    slots = np.fromiter((slot for slot, _, _, _ in decoded), dtype=np.int64, count=len(decoded))
    kinds = blocks["i16"][slots, KIND]
    wrong = np.flatnonzero((kinds == VEHICLE) != (slots < max_vehicles))
    if wrong.size:
        slot = int(slots[wrong[0]])
        raise StateCorruptedError(
            f"entities: slot {slot} holds the wrong kind {int(kinds[wrong[0]])}"
        )
    # Every slot has a position by now (a required, non-None field): check them at once.
    columns = decoder.layout.columns["position"]
    positions = blocks["f64"][slots, columns.start : columns.stop]
    finite = np.isfinite(positions).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise StateCorruptedError(
            f"entity slot {int(slots[bad])}: non-finite position {positions[bad]}"
        )
    vehicles, objects = [], []
    for slot, kind, obj, refs in decoded:
        if kind == VEHICLE and not isinstance(obj, Vehicle):
            raise StateCorruptedError(
                f"entities: slot {slot} of road.vehicles holds class {type(obj).__qualname__}, "
                "not a Vehicle: its class id is corrupted"
            )
        for name, target in refs.items():
            if target not in by_slot:
                # Name the kind: a corrupted kind column empties the slot referred to.
                what = (
                    f"which is empty (kind {int(blocks['i16'][target, KIND])})"
                    if 0 <= target < blocks["i16"].shape[0]
                    else "outside the table"
                )
                raise StateCorruptedError(
                    f"entities.{name} of slot {slot} refers to slot {target}, {what}"
                )
            obj.__dict__[name] = by_slot[target]
        try:
            rebuild_derived(core, obj, slot, history_sizes)
        except (AttributeError, TypeError, ValueError) as err:
            raise StateCorruptedError(f"entity slot {slot} cannot be rebuilt: {err}") from err
        (vehicles if kind == VEHICLE else objects).append(obj)
    return vehicles, objects, by_slot


def rebuild_derived(core: Any, obj: Any, slot: int, history_sizes: dict[type, int | None]) -> None:
    """Attach a decoded object to ``core``'s road and rebuild what is not stored.

    Its lane object (from its lane index), its render-only buffers (``log``,
    ``history``) and a BicycleVehicle's linearised dynamics.

    Args:
        core: the unwrapped env.
        obj: the decoded road object.
        slot: its slot (named in errors).
        history_sizes: a cache of each class's ``HISTORY_SIZE``.

    Raises:
        StateCorruptedError: its lane is not on this road.

    Example:
        >>> import gymnasium as gym
        >>> env = gym.make("merge-v0")
        >>> _ = env.reset(seed=0)
        >>> vehicle = env.unwrapped.road.vehicles[1]
        >>> rebuild_derived(env.unwrapped, vehicle, 1, {})
        >>> vehicle.lane is env.unwrapped.road.network.get_lane(vehicle.lane_index)
        True
    """
    d = obj.__dict__
    d["road"] = core.road
    lane_index = d["lane_index"]  # required: checked by the layout
    try:
        d["lane"] = None if lane_index is None else core.road.network.get_lane(lane_index)
    except (KeyError, IndexError) as err:
        raise StateCorruptedError(
            f"entity slot {slot}: lane {lane_index} is not on this road"
        ) from err
    cls = type(obj)
    if cls not in history_sizes:
        history_sizes[cls] = getattr(cls, "HISTORY_SIZE", None)
    history = history_sizes[cls]
    if history is not None:
        d["log"] = []
        d["history"] = deque(maxlen=history)
    if isinstance(obj, BicycleVehicle):
        d["A_lat"], d["B_lat"] = obj.lateral_lpv_dynamics()  # also sets theta
