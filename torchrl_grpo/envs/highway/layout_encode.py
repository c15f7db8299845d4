"""Packing road objects into a highway-env state's entity tables.

:class:`EntityEncoder` writes each object's attributes into its slot's rows of an
:class:`~torchrl_grpo.envs.highway.layout.EntityLayout`, through straight-line code
generated once per attribute pattern (one per class, in practice).
"""

from __future__ import annotations

import operator
from array import array
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from torchrl_grpo.envs.core.errors import SnapshotError, StateCapacityError, UnknownFieldError
from torchrl_grpo.envs.highway.layout import (
    CLASS_ID,
    DTYPES,
    EMPTY,
    KIND,
    TYPECODES,
    EntityLayout,
)
from torchrl_grpo.envs.highway.schema import DERIVED_ATTRIBUTES, Field

__all__ = ["EntityEncoder"]


class EntityEncoder:
    """Packs ``(slot, kind, object)`` items into the four blocks of a layout.

    Args:
        layout: the entity layout to write.

    Example:
        >>> from torchrl_grpo.envs.highway.schema import Field
        >>> layout = EntityLayout({"speed": Field("float")}, capacity=2, nodes=["a", "b"])
        >>> class Car:
        ...     def __init__(self, speed):
        ...         self.speed = speed
        >>> blocks = EntityEncoder(layout).encode([(0, 0, Car(3.5))], {Car: 0})
        >>> blocks["f64"].tolist()
        [[3.5], [0.0]]
    """

    def __init__(self, layout: EntityLayout) -> None:
        self.layout = layout
        self._writers = {name: self._make_writer(name, f) for name, f in layout.fields.items()}
        self._encoders: dict[tuple[str, ...], Callable | None] = {}
        empty = {b: array(TYPECODES[b], [0] * w) for b, w in layout.widths.items()}
        empty["i16"][KIND] = empty["i16"][CLASS_ID] = EMPTY
        self._empty_rows = empty

    def _make_writer(self, name: str, field: Field) -> Callable:
        layout = self.layout
        c = layout.columns[name]
        s, e = c.start, c.stop
        kind = field.kind
        lane_code = layout.lane_code
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
            n_len = layout.columns[name + "#len"].start
            max_route = layout.max_route

            def write(v, rows, slot_of):
                if len(v) > max_route:
                    raise StateCapacityError(
                        f"a route of {len(v)} segments; this env's state holds {max_route}"
                    )
                codes = array("h", [x for seg in v for x in lane_code(seg)])
                rows["i16"][s : s + 3 * len(v)] = codes
                rows["i16"][n_len] = len(v)
        elif kind == "speeds":
            n_len = layout.columns[name + "#len"].start
            is_int = layout.columns[name + "#int"].start
            max_speeds = layout.max_speeds

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
            n_len = layout.columns[name + "#len"].start

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
        blocks = {b: [empty[b]] * self.layout.capacity for b in self.layout.widths}
        slot_of = {id(obj): slot for slot, _, obj in items}
        for slot, kind, obj in items:
            cls = type(obj)
            class_id = class_index.get(cls)
            if class_id is None:
                raise _unregistered(cls)
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
            b: np.frombuffer(bytearray().join(rows), dtype=DTYPES[b]).reshape(
                self.layout.capacity, self.layout.widths[b]
            )
            for b, rows in blocks.items()
        }

    def check_names(self, objects: Iterable[Any], class_index: dict[type, int]) -> None:
        """Refuse an object whose class or an attribute's name the layout cannot store.

        What :meth:`encode` refuses by name, without packing anything: it serves where
        the objects cannot be packed (more of them than the layout has slots).

        Raises:
            UnknownFieldError: an object's class is not registered, or one of its
                attributes is neither a field nor derived on restore.

        Example:
            >>> from torchrl_grpo.envs.highway.schema import Field
            >>> layout = EntityLayout({"speed": Field("float")}, capacity=1, nodes=["a"])
            >>> class Car:
            ...     def __init__(self):
            ...         self.speed, self.mood = 3.5, "calm"
            >>> EntityEncoder(layout).check_names([Car(), Car()], {Car: 0})
            Traceback (most recent call last):
            ...
            torchrl_grpo.envs.core.errors.UnknownFieldError: Car.mood is not a field ...
        """
        for obj in objects:
            cls = type(obj)
            if cls not in class_index:
                raise _unregistered(cls)
            for name, value in vars(obj).items():
                if name not in self._writers and name not in DERIVED_ATTRIBUTES:
                    raise _unknown_attribute(cls, name, value)

    def _encode_slowly(self, obj: Any, rows: dict[str, array], slot_of: dict[int, int]) -> None:
        cls = type(obj)
        index = {n: i for i, n in enumerate(self.layout.names)}
        flags = rows["flags"]
        for name, value in vars(obj).items():
            writer = self._writers.get(name)
            if writer is None:
                if name in DERIVED_ATTRIBUTES:
                    continue
                raise _unknown_attribute(cls, name, value)
            flags[self.layout.present.start + index[name]] = True
            if value is None:
                flags[self.layout.is_none.start + index[name]] = True
                continue
            try:
                writer(value, rows, slot_of)
            except SnapshotError:
                raise
            except (TypeError, ValueError, KeyError, IndexError, OverflowError) as err:
                raise UnknownFieldError(
                    f"{cls.__qualname__}.{name} holds {value!r}, which does not fit its "
                    f"registered kind {self.layout.fields[name]}: {err}"
                ) from err

    def _compile_encoder(self, keys: tuple[str, ...]) -> Callable | None:
        """Straight-line code that packs objects whose ``__dict__`` has exactly ``keys``.

        Snapshots are taken on the hot path of branching; a generated function per
        attribute pattern (one per class, in practice) is several times faster than a
        loop over attributes. Returns ``None`` when an attribute is unknown.
        """
        index = {n: i for i, n in enumerate(self.layout.names)}
        namespace: dict[str, Any] = {"index": operator.index, "BOOLS": (bool, np.bool_)}
        lines = ["def encode(d, f, s, l, b, rows, slot_of):"]
        for name in keys:
            if name in DERIVED_ATTRIBUTES and name not in self.layout.fields:
                continue
            if name not in self.layout.fields:
                return None
            c, kind = self.layout.columns[name], self.layout.fields[name].kind
            i = index[name]
            lines += [
                f"    v = d[{name!r}]",
                f"    b[{self.layout.present.start + i}] = True",
                "    if v is None:",
                f"        b[{self.layout.is_none.start + i}] = True",
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


def _unregistered(cls: type) -> UnknownFieldError:
    return UnknownFieldError(
        f"road object class {cls.__module__}.{cls.__qualname__} is not registered; "
        "call torchrl_grpo.envs.register_vehicle_class before building the env"
    )


def _unknown_attribute(cls: type, name: str, value: Any) -> UnknownFieldError:
    return UnknownFieldError(
        f"{cls.__qualname__}.{name} is not a field the highway codec knows "
        f"(value {value!r}); register it with register_vehicle_class(cls, fields={{...}})"
    )
