"""The state-codec interface: a gymnasium env's complete state <-> a TensorDict of tensors.

A codec is what makes a simulator snapshottable for :class:`~torchrl_grpo.envs.SnapshotEnv`.
It knows which Python objects decide the simulator's future and how to write them
into fixed-shape tensors (so that states fit ``ParallelEnv`` shared buffers, replay
buffers and ``torch.save``), and how to put them back.

Implement one for your own gymnasium env by subclassing :class:`StateCodec`; see
:class:`~torchrl_grpo.envs.CartPoleStateCodec` for a complete 60-line example.
"""

from __future__ import annotations

import hashlib
import json
from abc import ABC, abstractmethod
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.errors import StateCorruptedError, StateMismatchError


class StateCodec(ABC):
    """Converts the complete state of one gymnasium env instance to tensors and back.

    A codec instance is bound to one env instance by :meth:`bind`, called once when
    the TorchRL env is built; afterwards :meth:`encode` and :meth:`decode` are called
    as often as snapshots are taken and restored.

    Contract:
        * :meth:`encode` returns a TensorDict that matches :meth:`state_spec` exactly
          (keys, shapes, dtypes) and holds only tensors.
        * :meth:`decode` validates *everything* before it modifies the env, and raises a
          :class:`~torchrl_grpo.envs.SnapshotError` subclass on bad input, leaving the
          env untouched.
        * ``decode(encode())`` followed by the same actions reproduces the original
          trajectory bit for bit.
        * :meth:`fingerprint` identifies the configuration a state belongs to; states
          are only restored into envs with the same fingerprint.

    Example:
        >>> import gymnasium as gym
        >>> from torchrl_grpo.envs import CartPoleStateCodec
        >>> env = gym.make("CartPole-v1")
        >>> _ = env.reset(seed=0)
        >>> codec = CartPoleStateCodec()
        >>> codec.bind(env)
        >>> state = codec.encode(env)
        >>> _ = env.step(0)
        >>> codec.decode(env, state)
        >>> bool((codec.encode(env) == state).all())
        True
    """

    def bind(self, env: gym.Env) -> None:  # noqa: B027 - optional hook, empty by design
        """Inspect a freshly reset env once (sizes, layout) before any encode/decode.

        Args:
            env: the gymnasium env (with its wrappers) this codec will serve.
        """

    @abstractmethod
    def state_spec(self) -> Composite:
        """The fixed spec of a state produced by :meth:`encode` (after :meth:`bind`)."""

    @abstractmethod
    def encode(self, env: gym.Env) -> TensorDictBase:
        """Capture the complete state of ``env`` as a new TensorDict of tensors."""

    @abstractmethod
    def decode(self, env: gym.Env, state: TensorDictBase) -> None:
        """Validate ``state`` fully, then write it into ``env``.

        Raises:
            SnapshotError: the state does not fit this env; ``env`` is unchanged.
        """

    def validate(self, env: gym.Env, state: TensorDictBase) -> None:
        """Run every check :meth:`decode` runs, without modifying ``env``.

        Lets a caller check states in its own process before sending them to the
        workers of a batched env (an error inside a ``ParallelEnv`` worker kills it).
        The default checks the fingerprint and the layout; codecs whose ``decode``
        checks more should override it.

        Raises:
            SnapshotError: the state does not fit this env.
        """
        self.check_compatible(state)
        check_state_layout(state, self.state_spec())

    def check_compatible(self, state: TensorDictBase) -> None:  # noqa: B027 - optional hook
        """Raise :class:`~torchrl_grpo.envs.StateMismatchError` for a foreign state.

        Called before any other check, so that a state captured from another
        configuration is reported as such rather than as a malformed state.
        """

    def reseed(self, state: TensorDictBase, seed: int) -> TensorDictBase:
        """Return a new state whose simulator random generator restarts from ``seed``.

        Everything else in the state (positions, time, counters) is unchanged, so the
        restored simulator is the same scene with a fresh random stream: the PCG64
        stream of ``seed``, as ``numpy.random.default_rng(seed)`` and gymnasium's
        ``reset(seed=seed)`` build it. ``state`` is left untouched.

        Codecs whose simulator keeps a generator in the state override this; the
        default raises, naming the codec.

        Args:
            state: an unbatched state from :meth:`encode`.
            seed: a non-negative int.

        Raises:
            NotImplementedError: this codec does not know where its generator is.

        Example:
            >>> from torchrl_grpo.envs import SnapshotEnv
            >>> env = SnapshotEnv("CartPole-v1", seed=0)
            >>> sim = env.get_state()["sim"]
            >>> new = env.codec.reseed(sim, 3)
            >>> from torchrl_grpo.envs import state_differences
            >>> state_differences(sim, new)
            ["'rng'"]
        """
        raise NotImplementedError(
            f"{type(self).__qualname__} cannot reseed states: override "
            "StateCodec.reseed to write a fresh generator for the seed into the state"
        )

    def fingerprint(self, env: gym.Env) -> int:
        """A 63-bit identifier of the configuration states of ``env`` belong to.

        The default hashes the env id and the codec class; override to include
        whatever makes two envs' states incompatible (a config, a road network).
        """
        spec_id = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
        return stable_hash(spec_id, type(self).__qualname__)


def stable_hash(*parts: Any) -> int:
    """Hash JSON-able parts to a non-negative int64, identical across processes.

    Python's ``hash`` is salted per process; this one is not, so a state's
    fingerprint survives ``torch.save`` and a trip to another worker.

    Example:
        >>> stable_hash("highway-fast-v0", {"lanes_count": 3}) == stable_hash(
        ...     "highway-fast-v0", {"lanes_count": 3})
        True
    """
    text = json.dumps(parts, sort_keys=True, default=_json_default)
    digest = hashlib.blake2b(text.encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & (2**63 - 1)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (set, frozenset)):
        return sorted(map(str, obj))
    return repr(obj)


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
