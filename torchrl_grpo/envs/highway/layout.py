"""The packed, fixed-shape table of road objects inside a highway-env state.

Each road object occupies one row (a *slot*) of four blocks::

    f64   [M, Nf]  float64 (stored as int64 bit patterns): floats, vectors, the action
                   dict, target speeds
    i16   [M, Ni]  int16: slot kind, class id, lane codes, routes, enums, colours,
                   references, lengths of variable-size fields
    i64   [M, Nl]  int64: integer fields (speed_index, yield_timer)
    flags [M, Nb]  bool: bool fields, then ``present`` and ``is_none`` per field

Packing keeps a state small (fewer bytes than pickling the env) and quick to
build (four tensors instead of one per field). :meth:`EntityLayout.column` reads
one named field back out of a state for users who want to look inside. This module
lays the columns out; :mod:`.layout_encode` packs objects into them and
:mod:`.layout_decode` builds objects back from them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchrl_grpo.envs.core.errors import (
    StateCapacityError,
    StateCorruptedError,
)
from torchrl_grpo.envs.highway.schema import MAX_COLOR, Field

NONE = -1  # encodes None in integer slots (lane ids, references)
KIND, CLASS_ID = 0, 1  # the first two i16 columns of every slot
EMPTY, VEHICLE, OBJECT = -1, 0, 1  # values of the kind column

DTYPES = {"f64": np.float64, "i16": np.int16, "i64": np.int64, "flags": np.bool_}
# Rows are built as typed arrays of these codes: they join into one buffer that numpy
# reads as is, where np.array() of nested lists converts element by element.
_MAX_LANE_CODES = 4096  # validated lane codes an EntityLayout remembers
TYPECODES = {"f64": "d", "i16": "h", "i64": "q", "flags": "B"}


@dataclass(frozen=True)
class Columns:
    """Where one field (or one of its companions) lives: a block and a column range."""

    block: str
    start: int
    width: int

    @property
    def stop(self) -> int:
        """End of the column range."""
        return self.start + self.width


class EntityLayout:
    """Packs road objects into rows and unpacks rows into new road objects.

    Args:
        fields: the field vocabulary (name -> :class:`Field`), fixed for this layout.
        capacity: number of slots.
        nodes: the road network's node names; lane codes index into them.
        max_route: segments a route may hold.
        max_speeds: entries a target-speed array may hold.
        required: fields every decoded object must have; :meth:`decode` refuses a slot
            whose presence flags lack one (the object would fail later, mid-step).
            A callable gives them per class (``cls -> fields``).
        not_none: fields that must not be ``None`` where they are present.
        lanes: the lane count of every ``(from, to)`` edge of the road network, by node
            names; lane codes off these edges are refused (``None``: not checked).
        max_magnitude: the largest magnitude a decoded float may hold (larger ones and
            NaN / inf are refused).
        domains: closed ranges narrower than that for some float fields, by name.

    Example:
        >>> from torchrl_grpo.envs.highway.schema import Field
        >>> layout = EntityLayout({"speed": Field("float")}, capacity=2, nodes=["a", "b"])
        >>> layout.widths["f64"]
        1
    """

    def __init__(
        self,
        fields: dict[str, Field],
        capacity: int,
        nodes: list,
        max_route: int = 16,
        max_speeds: int = 8,
        required: frozenset[str] | Callable[[type], frozenset[str]] = frozenset(),
        not_none: Iterable[str] = (),
        lanes: dict[tuple, int] | None = None,
        max_magnitude: float = math.inf,
        domains: dict[str, tuple[float, float]] | None = None,
    ) -> None:
        self.fields = dict(fields)
        self.names = list(self.fields)
        self.capacity = capacity
        self.nodes = list(nodes)
        self.node_index = {node: i for i, node in enumerate(self.nodes)}
        if len(self.nodes) > np.iinfo(np.int16).max:
            raise StateCapacityError(f"a road network of {len(self.nodes)} nodes is too large")
        self.max_route = max_route
        self.max_speeds = max_speeds
        self.required = required if callable(required) else frozenset(required)
        self.not_none = frozenset(not_none)
        self.max_magnitude = max_magnitude
        self.domains = dict(domains or {})
        self.lanes = (
            None
            if lanes is None
            else {
                (self.node_index[a], self.node_index[b]): n
                for (a, b), n in lanes.items()
                if a in self.node_index and b in self.node_index
            }
        )
        self.widths = {"f64": 0, "i16": 2, "i64": 0, "flags": 0}
        self.columns: dict[str, Columns] = {}
        for name, field in self.fields.items():
            for suffix, block, width in self._field_blocks(field):
                self.columns[name + suffix] = self._allocate(block, width)
        n = len(self.names)
        self.present = self._allocate("flags", n)
        self.is_none = self._allocate("flags", n)
        # Lane codes already validated, with the lane index each stands for: a scene
        # repeats a few lanes across all its vehicles.
        self._lane_indices: dict[tuple[int, int, int], tuple] = {}

    # ------------------------------------------------------------------ layout
    def _field_blocks(self, field: Field) -> list[tuple[str, str, int]]:
        kind = field.kind
        if kind in ("float", "vec2", "action", "array"):
            width = {"float": 1, "vec2": 2, "action": 2}.get(kind) or math.prod(field.shape)
            return [("", "f64", width)]
        if kind == "int":
            return [("", "i64", 1)]
        if kind == "bool":
            return [("", "flags", 1)]
        if kind == "speeds":
            return [("", "f64", self.max_speeds), ("#len", "i16", 1), ("#int", "flags", 1)]
        if kind == "lane":
            return [("", "i16", 3)]
        if kind == "route":
            return [("", "i16", 3 * self.max_route), ("#len", "i16", 1)]
        if kind == "color":
            return [("", "i16", MAX_COLOR), ("#len", "i16", 1)]
        return [("", "i16", 1)]  # ref, enum

    def _allocate(self, block: str, width: int) -> Columns:
        columns = Columns(block, self.widths[block], width)
        self.widths[block] += width
        return columns

    def spec_shapes(self) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
        """Shape and dtype of each block tensor."""
        torch_dtypes = {
            "f64": torch.float64,
            "i16": torch.int16,
            "i64": torch.int64,
            "flags": torch.bool,
        }
        return {b: ((self.capacity, w), torch_dtypes[b]) for b, w in self.widths.items()}

    def column(self, entities: Any, name: str) -> torch.Tensor:
        """The values of field ``name`` for every slot of a state's ``entities`` block.

        Args:
            entities: ``state["sim", "entities"]`` (any batch shape).
            name: a field name, optionally with a companion suffix (``"route#len"``).

        Example:
            >>> from torchrl_grpo.envs import HighwayEnv
            >>> env = HighwayEnv("merge-v0", seed=0)
            >>> state = env.get_state()
            >>> speeds = env.codec.layout.column(state["sim", "entities"], "speed")
            >>> speeds.shape
            torch.Size([6])
        """
        c = self.columns[name]
        values = entities[c.block][..., c.start : c.stop]
        if c.block == "f64":
            values = values.view(torch.float64)  # stored as int64 bit patterns
        return values.squeeze(-1) if c.width == 1 else values

    # ------------------------------------------------------------------ encode
    def lane_code(self, lane_index: tuple | None) -> tuple[int, int, int]:
        """The three integers a lane index ``(from, to, id)`` is stored as."""
        if lane_index is None:
            return (NONE, NONE, NONE)
        start, end, lane_id = lane_index
        return (self.node_index[start], self.node_index[end], NONE if lane_id is None else lane_id)

    # ------------------------------------------------------------------ decode
    def lane_index(
        self, code: list[int] | tuple[int, ...], where: str, one_lane: bool = False
    ) -> tuple:
        """The lane index a lane code stands for (validated).

        ``one_lane``: the code must name one lane (a vehicle's lane), not a whole road
        edge ``(from, to, None)`` as a route's segments do.
        """
        a, b, lane_id = code
        n = len(self.nodes)
        if not (0 <= a < n and 0 <= b < n) or lane_id < (0 if one_lane else NONE):
            raise StateCorruptedError(f"{where}: lane code {list(code)} is not on this road")
        if self.lanes is not None and ((a, b) not in self.lanes or lane_id >= self.lanes[(a, b)]):
            index = (self.nodes[a], self.nodes[b], None if lane_id == NONE else lane_id)
            raise StateCorruptedError(f"{where}: lane {index} is not on this road")
        return (self.nodes[a], self.nodes[b], None if lane_id == NONE else lane_id)

    def lane_at(self, a: int, b: int, lane_id: int, where: str, one_lane: bool = False) -> tuple:
        """:meth:`lane_index` of the code ``(a, b, lane_id)``, remembered once validated."""
        key = (a, b, lane_id)
        index = self._lane_indices.get(key)
        if index is None or (one_lane and lane_id < 0):
            index = self.lane_index(key, where, one_lane)
            if len(self._lane_indices) < _MAX_LANE_CODES:  # bounded: lane ids are not
                self._lane_indices[key] = index
        return index
