"""Unpacking a highway-env state's entity tables into new road objects.

:class:`EntityDecoder` builds new, unattached objects from the rows of an
:class:`~torchrl_grpo.envs.highway.layout.EntityLayout`, checking every value, through
straight-line code generated once per presence pattern (one per class, in practice).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from torchrl_grpo.envs.core.errors import StateCorruptedError
from torchrl_grpo.envs.highway.layout import CLASS_ID, EMPTY, KIND, OBJECT, EntityLayout
from torchrl_grpo.envs.highway.schema import MAX_COLOR, Field

__all__ = ["EntityDecoder"]


class EntityDecoder:
    """Builds new objects from the packed rows of a layout's blocks.

    Args:
        layout: the entity layout to read.

    Example:
        >>> from torchrl_grpo.envs.highway.layout_encode import EntityEncoder
        >>> from torchrl_grpo.envs.highway.schema import Field
        >>> layout = EntityLayout({"speed": Field("float")}, capacity=2, nodes=["a", "b"])
        >>> class Car:
        ...     pass
        >>> car = Car()
        >>> car.speed = 3.5
        >>> blocks = EntityEncoder(layout).encode([(0, 0, car)], {Car: 0})
        >>> [(slot, obj.speed) for slot, _, obj, _ in EntityDecoder(layout).decode(blocks, [Car])]
        [(0, 3.5)]
    """

    def __init__(self, layout: EntityLayout) -> None:
        self.layout = layout
        self._readers = {name: self._make_reader(name, f) for name, f in layout.fields.items()}
        # The range of each float column: the layout's magnitude, or the field's domain.
        width = layout.widths["f64"]
        self._low = np.full(width, -layout.max_magnitude)
        self._high = np.full(width, layout.max_magnitude)
        for name, (low, high) in layout.domains.items():
            c = layout.columns.get(name)
            if c is not None and c.block == "f64":
                self._low[c.start : c.stop] = max(low, -layout.max_magnitude)
                self._high[c.start : c.stop] = min(high, layout.max_magnitude)
        # Per presence pattern: its generated decoder and the required fields it lacks.
        self._plans: dict[tuple, tuple[Callable, str, np.ndarray]] = {}

    def _make_reader(self, name: str, field: Field) -> Callable:
        layout = self.layout
        c = layout.columns[name]
        s, e = c.start, c.stop
        kind = field.kind
        lane_at = layout.lane_at
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
            return lambda rows: lane_at(*rows["i16"][s:e], where, True)
        if kind == "route":
            n_len, max_route = layout.columns[name + "#len"].start, layout.max_route

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
            n_len = layout.columns[name + "#len"].start
            is_int = layout.columns[name + "#int"].start
            max_speeds = layout.max_speeds

            def read(rows):
                n = rows["i16"][n_len]
                # MDPVehicle indexes its target speeds: an empty array fails mid-step
                if not 1 <= n <= max_speeds:
                    raise StateCorruptedError(f"{where}: length {n} outside [1, {max_speeds}]")
                values = np.array(rows["f64"][s : s + n])
                return values.astype(np.int64) if rows["flags"][is_int] else values

            return read
        if kind == "color":
            n_len = layout.columns[name + "#len"].start

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
        as_lists = {b: blocks[b].tolist() for b in self.layout.widths}
        kinds = blocks["i16"][:, KIND]
        class_ids = blocks["i16"][:, CLASS_ID]
        if ((kinds < EMPTY) | (kinds > OBJECT)).any():
            raise StateCorruptedError("entities: a slot kind is not -1, 0 or 1")
        used = np.flatnonzero(kinds != EMPTY)
        wrong = (class_ids[used] < 0) | (class_ids[used] >= len(classes))
        if wrong.any():
            slot = int(used[np.flatnonzero(wrong)[0]])
            raise StateCorruptedError(
                f"entities: slot {slot} (kind {int(kinds[slot])}) has class id "
                f"{int(class_ids[slot])}, outside [0, {len(classes)}): its kind or class id "
                "is corrupted"
            )
        p0, n0, n = self.layout.present.start, self.layout.is_none.start, len(self.layout.names)
        out, float_masks = [], []
        for slot in used.tolist():
            f, s, ints, b = (as_lists[blk][slot] for blk in ("f64", "i16", "i64", "flags"))
            cls = classes[s[CLASS_ID]]
            decoder, lacking, floats = self._decoder(
                cls, tuple(b[p0 : p0 + n]), tuple(b[n0 : n0 + n])
            )
            if lacking:
                raise StateCorruptedError(
                    f"entity slot {slot} (class {cls.__qualname__}) {lacking}: its class id "
                    "or its presence flags are corrupted"
                )
            float_masks.append(floats)
            obj = cls.__new__(cls)
            values, refs = decoder(f, s, ints, b, {"f64": f, "i16": s, "i64": ints, "flags": b})
            obj.__dict__.update(values)
            out.append((slot, s[KIND], obj, refs))
        if out:
            self._check_floats(blocks["f64"][used], np.stack(float_masks), used)
        return out

    def _check_floats(self, values: np.ndarray, read: np.ndarray, slots: np.ndarray) -> None:
        # Every float a slot's objects read: finite and within the layout's magnitude
        # (NaN fails the comparison too). One vectorised test for the whole table.
        bad = read & ~((values >= self._low) & (values <= self._high))
        if bad.any():
            row, column = (int(i[0]) for i in np.nonzero(bad))
            name = next(
                k
                for k, c in self.layout.columns.items()
                if c.block == "f64" and c.start <= column < c.stop
            )
            raise StateCorruptedError(
                f"entities.{name.split('#')[0]} of slot {int(slots[row])} is "
                f"{values[row, column]!r}: outside [{self._low[column]:g}, "
                f"{self._high[column]:g}], or not finite"
            )

    def _decoder(
        self, cls: type, present: tuple[bool, ...], is_none: tuple[bool, ...]
    ) -> tuple[Callable, str, np.ndarray]:
        # Objects of one class share their presence pattern: generate its decoder once
        # (straight-line code, like the encoders), and check its required fields once.
        key = (cls, *present, *is_none)
        plan = self._plans.get(key)
        if plan is None:
            layout = self.layout
            here = {n for n, p in zip(layout.names, present, strict=True) if p}
            nones = {n for n, p in zip(layout.names, is_none, strict=True) if p and n in here}
            required = layout.required(cls) if callable(layout.required) else layout.required
            missing, unset = sorted(required - here), sorted(nones & layout.not_none)
            lacking = (
                f"lacks the required fields {missing}"
                if missing
                else (f"holds None in {unset}" if unset else "")
            )
            floats = np.zeros(layout.widths["f64"], dtype=np.bool_)
            for name in here - nones:
                c = layout.columns[name]
                if c.block == "f64":
                    floats[c.start : c.stop] = True
            namespace: dict[str, Any] = {"array": np.array, "LANE": self.layout.lane_at}
            values, refs = [], []
            for i, (name, here, none) in enumerate(
                zip(self.layout.names, present, is_none, strict=True)
            ):
                if not here:
                    continue
                c, kind = self.layout.columns[name], self.layout.fields[name].kind
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
                        f"{where!r}, True)"
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
            plan = self._plans[key] = (namespace["decode"], lacking, floats)
        return plan
