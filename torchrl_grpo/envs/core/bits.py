"""Tensor states as data: floats as bit patterns, layouts, comparison, flat <-> nested.

Helpers every codec and snapshot env shares. States keep floating-point values as the
integer bit patterns of the same width (:func:`to_bits`, :func:`from_bits`), so that
copies, ``torch.save`` and shared buffers keep every bit (NaN payloads included), and
:func:`states_equal` compares states bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.core.errors import StateCorruptedError, StateMismatchError

SpecLayout = dict[Any, tuple[torch.Size, torch.dtype]]

# States hold floating-point values as integer bit patterns of the same width:
# tensordict's clone() copies floats through ``x + 0``, which turns -0.0 into +0.0,
# and a state must survive every copy bit for bit.
FLOAT_BITS: dict[torch.dtype, torch.dtype] = {
    torch.float64: torch.int64,
    torch.float32: torch.int32,
    torch.float16: torch.int16,
    torch.bfloat16: torch.int16,
}


def bits_spec(spec: Composite) -> tuple[Composite, dict[Any, torch.dtype]]:
    """A copy of ``spec`` whose floating leaves are integers of the same width.

    Returns:
        The integer spec and ``{key: original float dtype}`` of the converted leaves.

    Example:
        >>> from torchrl.data import Composite, Unbounded
        >>> spec, floats = bits_spec(Composite(x=Unbounded((2,), dtype=torch.float64)))
        >>> spec["x"].dtype, floats
        (torch.int64, {'x': torch.float64})
    """
    out = spec.clone()
    floats = {}
    for key in spec.keys(True, True):
        leaf = spec[key]
        if leaf.dtype in FLOAT_BITS:
            floats[key] = leaf.dtype
            out[key] = Unbounded(leaf.shape, dtype=FLOAT_BITS[leaf.dtype], device=leaf.device)
    return out, floats


def to_bits(tensor: torch.Tensor) -> torch.Tensor:
    """View a floating tensor as integers of the same width (other tensors pass through).

    Example:
        >>> to_bits(torch.tensor([-0.0], dtype=torch.float64)).item() == -(2**63)
        True
    """
    bits = FLOAT_BITS.get(tensor.dtype)
    return tensor if bits is None else tensor.view(bits)


def from_bits(tensor: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Inverse of :func:`to_bits`: view integer bit patterns as ``dtype``.

    States store floats as their bit patterns (so that a comparison is bitwise and
    NaN payloads survive); read a float field of a state through this.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> state = HighwayEnv("merge-v0", seed=0).get_state()
        >>> from_bits(state["sim", "env", "time"], torch.float64).item()
        0.0
    """
    return tensor if tensor.dtype == dtype else tensor.view(dtype)


def check_finite_floats(
    leaves: dict[Any, torch.Tensor],
    float_dtypes: dict[Any, torch.dtype],
    where: str,
    nan_allowed: frozenset[str] = frozenset(),
) -> None:
    """Raise :class:`StateCorruptedError` naming the first float leaf holding a NaN or inf.

    Args:
        leaves: a state's leaves by key (floats as bit patterns).
        float_dtypes: the float dtype of each leaf stored as bits, by key.
        where: the part of the state, named in the error.
        nan_allowed: top-level keys whose NaN means "not reported" (inf is still refused).

    Example:
        >>> x = to_bits(torch.tensor([0.5, float("nan")], dtype=torch.float64))
        >>> try:
        ...     check_finite_floats({"x": x}, {"x": torch.float64}, "output")
        ... except StateCorruptedError as err:
        ...     print(err)
        output.x holds nan: not finite
    """
    for key, dtype in float_dtypes.items():
        values = from_bits(leaves[key], dtype)
        path = key if isinstance(key, tuple) else (key,)
        ok = ~values.isinf() if path[0] in nan_allowed else values.isfinite()
        if not bool(ok.all()):
            bad = values[~ok][0].item()
            raise StateCorruptedError(f"{where}.{'.'.join(path)} holds {bad}: not finite")


def spec_layout(spec: Composite) -> SpecLayout:
    """The ``{key: (shape, dtype)}`` of every leaf of a spec, for fast repeated checks.

    Example:
        >>> from torchrl.data import Composite, Unbounded
        >>> spec_layout(Composite(x=Unbounded((2,))))
        {'x': (torch.Size([2]), torch.float32)}
    """
    return {key: (spec[key].shape, spec[key].dtype) for key in spec.keys(True, True)}


def check_state_layout(
    state: TensorDictBase, spec: Composite | SpecLayout
) -> dict[Any, torch.Tensor]:
    """Raise :class:`StateCorruptedError` unless ``state`` has the spec's keys, shapes, dtypes.

    Args:
        state: a candidate state.
        spec: the spec it must match, or its precomputed :func:`spec_layout`.

    Returns:
        The state's leaves by spec key, for callers that go on to read them.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Composite, Unbounded
        >>> spec = Composite(x=Unbounded((2,), dtype=torch.float64))
        >>> _ = check_state_layout(TensorDict(x=torch.zeros(2, dtype=torch.float64)), spec)
    """
    if not isinstance(state, TensorDictBase):
        raise StateCorruptedError(f"a state must be a TensorDict, got {type(state).__name__}")
    layout = spec_layout(spec) if isinstance(spec, Composite) else spec
    found: dict[Any, Any] = {}
    _collect_leaves(state, (), found)
    # One comparison of the key sets on the hot path; the differences only on failure.
    if found.keys() != layout.keys():
        missing = sorted(map(str, layout.keys() - found.keys()))
        if missing:
            raise StateCorruptedError(f"the state is truncated: missing entries {missing}")
        extra = sorted(map(str, found.keys() - layout.keys()))
        raise StateMismatchError(
            f"the state has entries this env does not know: {extra} "
            "(was it captured from another kind of env?)"
        )
    for key, (shape, dtype) in layout.items():
        value = found[key]
        if not isinstance(value, torch.Tensor):
            raise StateCorruptedError(f"state entry {key!r} is not a tensor")
        if value.dtype != dtype or value.shape != shape:
            raise StateCorruptedError(
                f"state entry {key!r} has shape {tuple(value.shape)} and dtype {value.dtype}, "
                f"expected {tuple(shape)} and {dtype}"
            )
    return found


def states_equal(a: TensorDictBase, b: TensorDictBase) -> bool:
    """Bitwise equality of two states: same keys, dtypes, shapes and bytes (NaN == NaN).

    Args:
        a: a state.
        b: another state.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> s = TensorDict(x=torch.tensor([float("nan"), 0.0]))
        >>> states_equal(s, s.clone())
        True
        >>> states_equal(s, TensorDict(x=torch.tensor([float("nan"), -0.0])))
        False
    """
    return not state_differences(a, b)


def state_differences(a: TensorDictBase, b: TensorDictBase) -> list[str]:
    """The keys at which two states differ bitwise (empty when they are identical).

    Args:
        a: a state.
        b: another state.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> state_differences(TensorDict(x=torch.ones(1)), TensorDict(x=torch.zeros(1)))
        ["'x'"]
    """
    keys_a = set(a.keys(True, True))
    keys_b = set(b.keys(True, True))
    diffs = [f"{k!r} (only in one state)" for k in sorted(map(str, keys_a ^ keys_b))]
    for key in keys_a & keys_b:
        x, y = a.get(key), b.get(key)
        if x.dtype != y.dtype or x.shape != y.shape:
            diffs.append(repr(key))
            continue
        if x.dtype.is_floating_point and x.numel():
            # Compare the bit patterns: catches -0.0 vs 0.0 and keeps NaN == NaN.
            x = x.contiguous().reshape(-1).view(torch.uint8)
            y = y.contiguous().reshape(-1).view(torch.uint8)
        if not torch.equal(x, y):
            diffs.append(repr(key))
    return sorted(diffs)


def leaves(td: TensorDictBase, prefix: tuple[str, ...] = ()):
    """Yield ``(key_tuple, tensor)`` for every leaf; quicker than ``items(True, True)``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> [k for k, _ in leaves(TensorDict(a=TensorDict(b=torch.ones(1))))]
        [('a', 'b')]
    """
    for key, value in td.items():
        if isinstance(value, TensorDictBase):
            yield from leaves(value, (*prefix, key))
        else:
            yield (*prefix, key), value


def _collect_leaves(td: TensorDictBase, prefix: tuple[str, ...], out: dict[Any, Any]) -> None:
    # The keys of check_state_layout: a top-level leaf by its name, a nested one by its
    # tuple (as spec_layout names them). A plain recursion: a generator costs more.
    for key, value in td.items():
        if isinstance(value, TensorDictBase):
            _collect_leaves(value, (*prefix, key), out)
        else:
            out[(*prefix, key) if prefix else key] = value


def as_numpy(state: TensorDictBase) -> dict[str, np.ndarray]:
    """Flatten a state into ``{"a.b": ndarray}`` views (no copy for CPU tensors)."""
    return {".".join(k): v.detach().cpu().numpy() for k, v in leaves(state)}


def nested_tensordict(flat: dict[tuple[str, ...], torch.Tensor]) -> TensorDict:
    """Build an unbatched TensorDict from ``{key_tuple: tensor}`` without validation.

    Snapshots are built on the hot path: the public constructor validates every leaf,
    which costs ten times more than the snapshot's own encoding of a small scenario.
    The caller guarantees unbatched tensors on one device.

    Example:
        >>> import torch
        >>> nested_tensordict({("a", "b"): torch.ones(2)})["a", "b"].shape
        torch.Size([2])
    """
    tree: dict = {}
    for key, value in flat.items():
        node = tree
        for part in key[:-1]:
            node = node.setdefault(part, {})
        node[key[-1]] = value
    return _tree_to_td(tree)


def _tree_to_td(tree: dict) -> TensorDict:
    return TensorDict._new_unsafe(
        {k: _tree_to_td(v) if isinstance(v, dict) else v for k, v in tree.items()},
        batch_size=torch.Size([]),
    )


def from_numpy(arrays: dict[str, np.ndarray]) -> TensorDict:
    """Build a state TensorDict from ``{"a.b": ndarray}`` in one pass (arrays are copied)."""
    return TensorDict(
        {tuple(k.split(".")): torch.from_numpy(np.array(v, copy=True)) for k, v in arrays.items()},
        batch_size=(),
    )


def flag_tensor(value: Any) -> torch.Tensor:
    """A new bool ``[1]`` tensor (through numpy: twice as fast as ``torch.tensor([value])``).

    Example:
        >>> flag_tensor(1)
        tensor([True])
    """
    return torch.from_numpy(np.array([bool(value)], dtype=np.bool_))


def float32_tensor(values: Any) -> torch.Tensor:
    """A new float32 tensor of ``values`` (rounded as ``torch.tensor(..., dtype=float32)``).

    Example:
        >>> float32_tensor([1.5, 2.0])
        tensor([1.5000, 2.0000])
    """
    return torch.from_numpy(np.array(values, dtype=np.float32))
