"""State every gymnasium env shares: its random generator and its wrappers' counters.

Codecs for particular simulators (highway-env, CartPole) build on these helpers so
that each of them stores the RNG and the ``TimeLimit`` / ``OrderEnforcing``
counters the same way.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.errors import SnapshotError, StateCorruptedError

_MASK32 = (1 << 32) - 1
RNG_WORDS = 10  # PCG64: state (4 x 32 bits), inc (4 x 32 bits), has_uint32, uinteger


def rng_spec() -> Unbounded:
    """Spec of an encoded PCG64 generator state."""
    return Unbounded((RNG_WORDS,), dtype=torch.int64)


def encode_rng(generator: np.random.Generator, out: np.ndarray) -> None:
    """Write a PCG64 generator's complete state into ``out`` (int64[RNG_WORDS]).

    Example:
        >>> import numpy as np
        >>> g = np.random.default_rng(0)
        >>> words = np.zeros(RNG_WORDS, dtype=np.int64)
        >>> encode_rng(g, words)
        >>> a = g.random()
        >>> restore_rng(g, words)
        >>> g.random() == a
        True
    """
    state = generator.bit_generator.state
    if state["bit_generator"] != "PCG64":
        raise SnapshotError(
            f"only PCG64 generators can be snapshotted, this env uses {state['bit_generator']}"
        )
    inner = state["state"]
    for i, value in enumerate((inner["state"], inner["inc"])):
        for j in range(4):
            out[4 * i + j] = (value >> (32 * j)) & _MASK32
    out[8] = state["has_uint32"]
    out[9] = state["uinteger"]


def decode_rng(words: np.ndarray) -> dict:
    """Validate encoded words and return the bit-generator state dict they describe."""
    if words.shape != (RNG_WORDS,) or (words < 0).any() or (words > _MASK32).any():
        raise StateCorruptedError("the random-generator words are out of range")
    state, inc = (sum(int(words[4 * i + j]) << (32 * j) for j in range(4)) for i in (0, 1))
    return {
        "bit_generator": "PCG64",
        "state": {"state": state, "inc": inc},
        "has_uint32": int(words[8]),
        "uinteger": int(words[9]),
    }


def restore_rng(generator: np.random.Generator, words: np.ndarray) -> None:
    """Restore a generator IN PLACE so every holder of the same object sees it."""
    generator.bit_generator.state = decode_rng(words)


def wrapper_spec() -> Composite:
    """Spec of the counters kept by gymnasium's standard wrappers."""
    return Composite(
        elapsed_steps=Unbounded((), dtype=torch.int64),
        has_reset=Unbounded((), dtype=torch.bool),
    )


def encode_wrappers(env: gym.Env) -> dict[str, np.ndarray]:
    """Capture ``TimeLimit._elapsed_steps`` (-1 when unset) and ``OrderEnforcing._has_reset``."""
    elapsed, has_reset = -1, True
    for wrapper in _wrappers(env):
        if isinstance(wrapper, gym.wrappers.TimeLimit):
            elapsed = -1 if wrapper._elapsed_steps is None else wrapper._elapsed_steps
        elif isinstance(wrapper, gym.wrappers.OrderEnforcing):
            has_reset = wrapper._has_reset
    return {
        "elapsed_steps": np.asarray(elapsed, dtype=np.int64),
        "has_reset": np.asarray(has_reset, dtype=np.bool_),
    }


def restore_wrappers(env: gym.Env, elapsed_steps: int, has_reset: bool) -> None:
    """Write wrapper counters back (the inverse of :func:`encode_wrappers`)."""
    for wrapper in _wrappers(env):
        if isinstance(wrapper, gym.wrappers.TimeLimit):
            wrapper._elapsed_steps = None if elapsed_steps < 0 else int(elapsed_steps)
        elif isinstance(wrapper, gym.wrappers.OrderEnforcing):
            wrapper._has_reset = bool(has_reset)


def _wrappers(env: gym.Env):
    while isinstance(env, gym.Wrapper):
        yield env
        env = env.env
