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
one named field back out of a state for users who want to look inside.
"""

from __future__ import annotations

import math
import operator
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchrl_grpo.envs.core.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    UnknownFieldError,
)
from torchrl_grpo.envs.highway.schema import DERIVED_ATTRIBUTES, MAX_COLOR, Field

NONE = -1  # encodes None in integer slots (lane ids, references)
KIND, CLASS_ID = 0, 1  # the first two i16 columns of every slot
EMPTY, VEHICLE, OBJECT = -1, 0, 1  # values of the kind column

_DTYPES = {"f64": np.float64, "i16": np.int16, "i64": np.int64, "flags": np.bool_}
# Rows are built as typed arrays of these codes: they join into one buffer that numpy
# reads as is, where np.array() of nested lists converts element by element.
_MAX_LANE_CODES = 4096  # validated lane codes an EntityLayout remembers
_TYPECODES = {"f64": "d", "i16": "h", "i64": "q", "flags": "B"}


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
        not_none: required fields that must not be ``None`` either.

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
        required: frozenset[str] = frozenset(),
        not_none: tuple[str, ...] = (),
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
        self.required = frozenset(required)
        self.not_none = tuple(not_none)
        self.widths = {"f64": 0, "i16": 2, "i64": 0, "flags": 0}
        self.columns: dict[str, Columns] = {}
        for name, field in self.fields.items():
            for suffix, block, width in self._field_blocks(field):
                self.columns[name + suffix] = self._allocate(block, width)
        n = len(self.names)
        self.present = self._allocate("flags", n)
        self.is_none = self._allocate("flags", n)
        self._writers = {name: self._make_writer(name, f) for name, f in self.fields.items()}
        self._readers = {name: self._make_reader(name, f) for name, f in self.fields.items()}
        # Per presence pattern: its generated decoder and the required fields it lacks.
        self._plans: dict[tuple[bool, ...], tuple[Callable, list[str]]] = {}
        self._encoders: dict[tuple[str, ...], Callable | None] = {}
        empty = {b: array(_TYPECODES[b], [0] * w) for b, w in self.widths.items()}
        empty["i16"][KIND] = empty["i16"][CLASS_ID] = EMPTY
        self._empty_rows = empty
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

    def _make_writer(self, name: str, field: Field) -> Callable:
        c = self.columns[name]
        s, e = c.start, c.stop
        kind = field.kind
        lane_code = self.lane_code
        # Writers convert as they store, so that a value of the wrong kind fails here,
        # inside encode()'s error handling, and not later in numpy.
        if kind == "float":

            def write(v, rows, slot_of):
                rows["f64"][s] = float(v)
        elif kind == "int":

            def write(v, rows, slot_of):
                rows["i64"][s] = operator.index(v)
        elif kind == "bool":

            def write(v, rows, slot_of):
                if not isinstance(v, (bool, np.bool_)):
                    raise TypeError(f"expected a bool, got {type(v).__name__}")
                rows["flags"][s] = bool(v)
        elif kind == "vec2":

            def write(v, rows, slot_of):
                x, y = v
                rows["f64"][s], rows["f64"][s + 1] = float(x), float(y)
        elif kind == "action":

            def write(v, rows, slot_of):
                rows["f64"][s] = float(v["steering"])
                rows["f64"][s + 1] = float(v["acceleration"])
        elif kind == "array":
            shape = field.shape

            def write(v, rows, slot_of):
                v = np.asarray(v, dtype=np.float64)
                if v.shape != shape:
                    raise ValueError(f"shape {v.shape}, expected {shape}")
                rows["f64"][s:e] = array("d", v.ravel().tolist())
        elif kind == "lane":

            def write(v, rows, slot_of):
                rows["i16"][s:e] = array("h", lane_code(v))
        elif kind == "route":
            n_len = self.columns[name + "#len"].start
            max_route = self.max_route

            def write(v, rows, slot_of):
                if len(v) > max_route:
                    raise StateCapacityError(
                        f"a route of {len(v)} segments; this env's state holds {max_route}"
                    )
                codes = array("h", [x for seg in v for x in lane_code(seg)])
                rows["i16"][s : s + 3 * len(v)] = codes
                rows["i16"][n_len] = len(v)
        elif kind == "speeds":
            n_len = self.columns[name + "#len"].start
            is_int = self.columns[name + "#int"].start
            max_speeds = self.max_speeds

            def write(v, rows, slot_of):
                v = np.asarray(v)
                if v.ndim != 1 or len(v) > max_speeds:
                    raise StateCapacityError(
                        f"target speeds of shape {v.shape}; this env's state holds {max_speeds}"
                    )
                rows["f64"][s : s + len(v)] = array("d", v.tolist())
                rows["i16"][n_len] = len(v)
                rows["flags"][is_int] = bool(np.issubdtype(v.dtype, np.integer))
        elif kind == "color":
            n_len = self.columns[name + "#len"].start

            def write(v, rows, slot_of):
                rows["i16"][s : s + len(v)] = array("h", v)
                rows["i16"][n_len] = len(v)
        elif kind == "ref":

            def write(v, rows, slot_of):
                rows["i16"][s] = slot_of[id(v)]
        else:  # enum
            choices = field.choices

            def write(v, rows, slot_of):
                rows["i16"][s] = choices.index(v)

        return write

    def encode(
        self, items: list[tuple[int, int, Any]], class_index: dict[type, int]
    ) -> dict[str, np.ndarray]:
        """Pack ``(slot, kind, object)`` items into the four blocks.

        Raises:
            UnknownFieldError: an object's class or one of its attributes is unknown.
        """
        empty = self._empty_rows
        # Unused slots all point at the one (never written) empty row of each block.
        blocks = {b: [empty[b]] * self.capacity for b in self.widths}
        slot_of = {id(obj): slot for slot, _, obj in items}
        for slot, kind, obj in items:
            cls = type(obj)
            class_id = class_index.get(cls)
            if class_id is None:
                raise UnknownFieldError(
                    f"road object class {cls.__module__}.{cls.__qualname__} is not registered; "
                    "call torchrl_grpo.envs.register_vehicle_class before building the env"
                )
            rows = {b: empty[b][:] for b in blocks}  # a copy of the empty row
            for b, row in rows.items():
                blocks[b][slot] = row
            rows["i16"][KIND], rows["i16"][CLASS_ID] = kind, class_id
            d = obj.__dict__
            encoder = self._encoders.get(tuple(d))
            if encoder is None:
                encoder = self._encoders[tuple(d)] = self._compile_encoder(tuple(d))
            try:
                if encoder is None:
                    raise KeyError("unknown attribute")
                encoder(d, rows["f64"], rows["i16"], rows["i64"], rows["flags"], rows, slot_of)
            except SnapshotError:
                raise
            except (TypeError, ValueError, KeyError, IndexError, OverflowError):
                # The straight-line encoder does not say which attribute failed: the
                # attribute-by-attribute path does, and raises the error that names it.
                self._encode_slowly(obj, rows, slot_of)
                raise
        return {
            b: np.frombuffer(bytearray().join(rows), dtype=_DTYPES[b]).reshape(
                self.capacity, self.widths[b]
            )
            for b, rows in blocks.items()
        }

    def _encode_slowly(self, obj: Any, rows: dict[str, array], slot_of: dict[int, int]) -> None:
        cls = type(obj)
        index = {n: i for i, n in enumerate(self.names)}
        flags = rows["flags"]
        for name, value in vars(obj).items():
            writer = self._writers.get(name)
            if writer is None:
                if name in DERIVED_ATTRIBUTES:
                    continue
                raise UnknownFieldError(
                    f"{cls.__qualname__}.{name} is not a field the highway codec knows "
                    f"(value {value!r}); register it with "
                    "register_vehicle_class(cls, fields={...})"
                )
            flags[self.present.start + index[name]] = True
            if value is None:
                flags[self.is_none.start + index[name]] = True
                continue
            try:
                writer(value, rows, slot_of)
            except SnapshotError:
                raise
            except (TypeError, ValueError, KeyError, IndexError, OverflowError) as err:
                raise UnknownFieldError(
                    f"{cls.__qualname__}.{name} holds {value!r}, which does not fit its "
                    f"registered kind {self.fields[name]}: {err}"
                ) from err

    def _compile_encoder(self, keys: tuple[str, ...]) -> Callable | None:
        """Straight-line code that packs objects whose ``__dict__`` has exactly ``keys``.

        Snapshots are taken on the hot path of branching; a generated function per
        attribute pattern (one per class, in practice) is several times faster than a
        loop over attributes. Returns ``None`` when an attribute is unknown.
        """
        index = {n: i for i, n in enumerate(self.names)}
        namespace: dict[str, Any] = {"index": operator.index, "BOOLS": (bool, np.bool_)}
        lines = ["def encode(d, f, s, l, b, rows, slot_of):"]
        for name in keys:
            if name in DERIVED_ATTRIBUTES and name not in self.fields:
                continue
            if name not in self.fields:
                return None
            c, kind = self.columns[name], self.fields[name].kind
            i = index[name]
            lines += [
                f"    v = d[{name!r}]",
                f"    b[{self.present.start + i}] = True",
                "    if v is None:",
                f"        b[{self.is_none.start + i}] = True",
                "    else:",
            ]
            if kind == "float":
                lines.append(f"        f[{c.start}] = float(v)")
            elif kind == "int":
                lines.append(f"        l[{c.start}] = index(v)")
            elif kind == "bool":
                lines += [
                    "        if not isinstance(v, BOOLS):",
                    "            raise TypeError('expected a bool')",
                    f"        b[{c.start}] = bool(v)",
                ]
            elif kind == "vec2":
                lines += [
                    "        x, y = v",
                    f"        f[{c.start}] = float(x)",
                    f"        f[{c.start + 1}] = float(y)",
                ]
            elif kind == "action":
                lines += [
                    f"        f[{c.start}] = float(v['steering'])",
                    f"        f[{c.start + 1}] = float(v['acceleration'])",
                ]
            else:
                namespace[f"w_{i}"] = self._writers[name]
                lines.append(f"        w_{i}(v, rows, slot_of)")
        exec("\n".join(lines), namespace)  # noqa: S102 - generated from the field table only
        return namespace["encode"]

    # ------------------------------------------------------------------ decode
    def lane_index(self, code: list[int] | tuple[int, ...], where: str) -> tuple:
        """The lane index a lane code stands for (validated)."""
        a, b, lane_id = code
        n = len(self.nodes)
        if not (0 <= a < n and 0 <= b < n) or lane_id < NONE:
            raise StateCorruptedError(f"{where}: lane code {list(code)} is not on this road")
        return (self.nodes[a], self.nodes[b], None if lane_id == NONE else lane_id)

    def lane_at(self, a: int, b: int, lane_id: int, where: str) -> tuple:
        """:meth:`lane_index` of the code ``(a, b, lane_id)``, remembered once validated."""
        key = (a, b, lane_id)
        index = self._lane_indices.get(key)
        if index is None:
            index = self.lane_index(key, where)
            if len(self._lane_indices) < _MAX_LANE_CODES:  # bounded: lane ids are not
                self._lane_indices[key] = index
        return index

    def _make_reader(self, name: str, field: Field) -> Callable:
        c = self.columns[name]
        s, e = c.start, c.stop
        kind = field.kind
        lane_at = self.lane_at
        where = f"entities.{name}"
        if kind == "float":
            return lambda rows: rows["f64"][s]
        if kind == "int":
            return lambda rows: rows["i64"][s]
        if kind == "bool":
            return lambda rows: rows["flags"][s]
        if kind == "vec2":
            return lambda rows: np.array(rows["f64"][s:e])
        if kind == "action":
            return lambda rows: {"steering": rows["f64"][s], "acceleration": rows["f64"][s + 1]}
        if kind == "array":
            shape = field.shape
            return lambda rows: np.array(rows["f64"][s:e]).reshape(shape)
        if kind == "lane":
            return lambda rows: lane_at(*rows["i16"][s:e], where)
        if kind == "route":
            n_len, max_route = self.columns[name + "#len"].start, self.max_route

            def read(rows):
                n = rows["i16"][n_len]
                if not 0 <= n <= max_route:
                    raise StateCorruptedError(f"{where}: length {n} outside [0, {max_route}]")
                codes = rows["i16"][s : s + 3 * n]
                return [
                    lane_at(codes[j], codes[j + 1], codes[j + 2], where) for j in range(0, 3 * n, 3)
                ]

            return read
        if kind == "speeds":
            n_len = self.columns[name + "#len"].start
            is_int = self.columns[name + "#int"].start
            max_speeds = self.max_speeds

            def read(rows):
                n = rows["i16"][n_len]
                if not 0 <= n <= max_speeds:
                    raise StateCorruptedError(f"{where}: length {n} outside [0, {max_speeds}]")
                values = np.array(rows["f64"][s : s + n])
                return values.astype(np.int64) if rows["flags"][is_int] else values

            return read
        if kind == "color":
            n_len = self.columns[name + "#len"].start

            def read(rows):
                n = rows["i16"][n_len]
                if not 0 <= n <= MAX_COLOR:
                    raise StateCorruptedError(f"{where}: length {n} outside [0, {MAX_COLOR}]")
                return tuple(rows["i16"][s : s + n])

            return read
        if kind == "ref":
            return lambda rows: rows["i16"][s]  # resolved to an object by the caller
        choices = field.choices

        def read(rows):
            code = rows["i16"][s]
            if not 0 <= code < len(choices):
                raise StateCorruptedError(f"{where}: {code} is not one of {choices}")
            return choices[code]

        return read

    def decode(
        self, blocks: dict[str, np.ndarray], classes: list[type]
    ) -> list[tuple[int, int, Any, dict[str, int]]]:
        """Build new, unattached objects from packed rows.

        Returns:
            ``(slot, kind, object, references)`` for every used slot, in slot order;
            ``references`` maps ``ref`` fields to the slot they point at.

        Raises:
            StateCorruptedError: a value is out of range, or a slot lacks a required
                field; nothing was modified.
        """
        as_lists = {b: blocks[b].tolist() for b in self.widths}
        kinds = blocks["i16"][:, KIND]
        class_ids = blocks["i16"][:, CLASS_ID]
        if ((kinds < EMPTY) | (kinds > OBJECT)).any():
            raise StateCorruptedError("entities: a slot kind is not -1, 0 or 1")
        used = np.flatnonzero(kinds != EMPTY)
        if ((class_ids[used] < 0) | (class_ids[used] >= len(classes))).any():
            raise StateCorruptedError(f"entities: a class id is outside [0, {len(classes)})")
        p0, n0, n = self.present.start, self.is_none.start, len(self.names)
        out = []
        for slot in used.tolist():
            f, s, ints, b = (as_lists[blk][slot] for blk in ("f64", "i16", "i64", "flags"))
            decoder, lacking = self._decoder(tuple(b[p0 : p0 + n]), tuple(b[n0 : n0 + n]))
            cls = classes[s[CLASS_ID]]
            if lacking:
                raise StateCorruptedError(
                    f"entity slot {slot} ({cls.__qualname__}) lacks required fields "
                    f"{lacking}: its presence flags are corrupted"
                )
            obj = cls.__new__(cls)
            values, refs = decoder(f, s, ints, b, {"f64": f, "i16": s, "i64": ints, "flags": b})
            obj.__dict__.update(values)
            out.append((slot, s[KIND], obj, refs))
        return out

    def _decoder(
        self, present: tuple[bool, ...], is_none: tuple[bool, ...]
    ) -> tuple[Callable, list[str]]:
        # Objects of one class share their presence pattern: generate its decoder once
        # (straight-line code, like the encoders), and check its required fields once.
        key = present + is_none
        plan = self._plans.get(key)
        if plan is None:
            here = {n for n, p in zip(self.names, present, strict=True) if p}
            nones = {n for n, p in zip(self.names, is_none, strict=True) if p}
            missing = sorted(self.required - here)
            lacking = missing or (sorted(self.not_none) if nones & set(self.not_none) else [])
            namespace: dict[str, Any] = {"array": np.array, "LANE": self.lane_at}
            values, refs = [], []
            for i, (name, here, none) in enumerate(zip(self.names, present, is_none, strict=True)):
                if not here:
                    continue
                c, kind = self.columns[name], self.fields[name].kind
                if none:
                    values.append(f"{name!r}: None")
                elif kind == "float":
                    values.append(f"{name!r}: f[{c.start}]")
                elif kind == "int":
                    values.append(f"{name!r}: l[{c.start}]")
                elif kind == "bool":
                    values.append(f"{name!r}: b[{c.start}]")
                elif kind == "vec2":
                    values.append(f"{name!r}: array(f[{c.start}:{c.stop}])")
                elif kind == "action":
                    values.append(
                        f"{name!r}: {{'steering': f[{c.start}], 'acceleration': f[{c.start + 1}]}}"
                    )
                elif kind == "lane":
                    where = f"entities.{name}"
                    values.append(
                        f"{name!r}: LANE(s[{c.start}], s[{c.start + 1}], s[{c.start + 2}], "
                        f"{where!r})"
                    )
                elif kind == "ref":
                    refs.append(f"{name!r}: s[{c.start}]")
                else:
                    namespace[f"r_{i}"] = self._readers[name]
                    values.append(f"{name!r}: r_{i}(rows)")
            source = (
                "def decode(f, s, l, b, rows):\n"
                f"    return {{{', '.join(values)}}}, {{{', '.join(refs)}}}"
            )
            exec(source, namespace)  # noqa: S102 - generated from the field table only
            plan = self._plans[key] = (namespace["decode"], lacking)
        return plan
