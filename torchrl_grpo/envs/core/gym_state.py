"""State every gymnasium env shares: its random generator and its wrappers' counters.

Codecs for particular simulators (highway-env, CartPole) build on these helpers so
that each of them stores the RNG and the ``TimeLimit`` / ``OrderEnforcing``
counters the same way.
"""

from __future__ import annotations

from numbers import Integral

import gymnasium as gym
import numpy as np
import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.core.errors import SnapshotError, StateCorruptedError

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


def invalid_rng_rows(words: torch.Tensor) -> torch.Tensor:
    """True where encoded words ``[..., RNG_WORDS]`` are no state :func:`decode_rng` accepts.

    The batched form of its checks: a word outside 32 bits, an even increment, or
    ``has_uint32`` other than 0 or 1.

    Example:
        >>> words = torch.stack([seeded_rng_words(0), torch.zeros(RNG_WORDS, dtype=torch.int64)])
        >>> invalid_rng_rows(words).tolist()
        [False, True]
    """
    bad = ((words < 0) | (words > _MASK32)).any(-1) | (words[..., 4] & 1 == 0)
    return bad | (words[..., 8] < 0) | (words[..., 8] > 1)


def check_rng_rows(words: torch.Tensor, rows: torch.Tensor) -> None:
    """Refuse ``[B, RNG_WORDS]`` words where ``rows`` is set and they are no numpy state.

    Raises:
        StateCorruptedError: :func:`decode_rng`'s message for the first such row,
            ``highway.rng of row <i>`` with ``i`` its index in ``words``.

    Example:
        >>> words = torch.stack([seeded_rng_words(0), torch.zeros(RNG_WORDS, dtype=torch.int64)])
        >>> check_rng_rows(words, torch.tensor([True, False]))  # row 1 is not read
    """
    for row in (invalid_rng_rows(words) & rows).nonzero().flatten()[:1].tolist():
        decode_rng(words[row].cpu().numpy(), f"highway.rng of row {row}")  # raises, naming it


def decode_rng(words: np.ndarray, where: str = "rng") -> dict:
    """Validate encoded words and return the bit-generator state dict they describe.

    Every word is a 32-bit value, the increment is odd (numpy's PCG64 always makes
    it so; a zeroed generator would return zeros forever and hang any rejection
    sampler that draws from it) and ``has_uint32`` is 0 or 1.

    Args:
        words: int64[RNG_WORDS] from :func:`encode_rng`.
        where: the state entry the words come from, named in errors.

    Raises:
        StateCorruptedError: naming ``where``.

    Example:
        >>> try:
        ...     decode_rng(np.zeros(RNG_WORDS, dtype=np.int64), "env.rng")
        ... except StateCorruptedError as err:
        ...     print(err)
        env.rng: the PCG64 increment is even (a zeroed generator?): not a state numpy makes
    """
    if words.shape != (RNG_WORDS,) or (words < 0).any() or (words > _MASK32).any():
        raise StateCorruptedError(f"{where}: the random-generator words are out of range")
    state, inc = (sum(int(words[4 * i + j]) << (32 * j) for j in range(4)) for i in (0, 1))
    if not inc & 1:
        raise StateCorruptedError(
            f"{where}: the PCG64 increment is even (a zeroed generator?): not a state numpy makes"
        )
    if words[8] not in (0, 1):
        raise StateCorruptedError(f"{where}: has_uint32 is {int(words[8])}, not 0 or 1")
    return {
        "bit_generator": "PCG64",
        "state": {"state": state, "inc": inc},
        "has_uint32": int(words[8]),
        "uinteger": int(words[9]),
    }


def restore_rng(generator: np.random.Generator, words: np.ndarray) -> None:
    """Restore a generator IN PLACE so every holder of the same object sees it."""
    generator.bit_generator.state = decode_rng(words)


def seeded_rng_words(seed: int) -> torch.Tensor:
    """The encoded state (int64[RNG_WORDS]) of a PCG64 generator freshly seeded with ``seed``.

    It is the generator ``numpy.random.default_rng(seed)`` builds, which is also the
    one gymnasium's ``env.reset(seed=seed)`` installs.

    Args:
        seed: a non-negative int.

    Example:
        >>> import numpy as np
        >>> g = np.random.default_rng()
        >>> restore_rng(g, seeded_rng_words(7).numpy())
        >>> g.random() == np.random.default_rng(7).random()
        True
    """
    if not isinstance(seed, Integral) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"a seed must be a non-negative int, got {seed!r}")
    words = np.zeros(RNG_WORDS, dtype=np.int64)
    encode_rng(np.random.default_rng(int(seed)), words)
    return torch.from_numpy(words)


def with_seeded_rng(state: TensorDictBase, key: NestedKey, seed: int) -> TensorDictBase:
    """A copy of a codec state whose generator words at ``key`` restart from ``seed``.

    The shared body of the codecs' :meth:`~torchrl_grpo.envs.StateCodec.reseed`.

    Args:
        state: an unbatched codec state (the ``"sim"`` part of an env state).
        key: where the codec keeps the encoded generator.
        seed: a non-negative int.

    Example:
        >>> from tensordict import TensorDict
        >>> state = TensorDict(rng=torch.zeros(RNG_WORDS, dtype=torch.int64))
        >>> new = with_seeded_rng(state, "rng", 7)
        >>> torch.equal(new["rng"], seeded_rng_words(7)), bool(state["rng"].any())
        (True, False)
    """
    if not isinstance(state, TensorDictBase):
        raise StateCorruptedError(f"a state must be a TensorDict, got {type(state).__name__}")
    if state.batch_dims:
        raise StateCorruptedError(
            f"reseed one state at a time, got batch size {tuple(state.batch_size)}"
        )
    current = state.get(key, None)
    if not isinstance(current, torch.Tensor) or current.shape != (RNG_WORDS,):
        raise StateCorruptedError(f"the state has no encoded generator at {key!r}")
    words = seeded_rng_words(seed)
    # States hold integers only (floats as bit patterns), so clone() keeps every bit.
    out = state.clone()
    out.set(key, words.to(current.device))
    return out


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


def check_wrappers(elapsed_steps: int, has_reset: bool, where: str = "wrappers") -> None:
    """Refuse wrapper counters no env can have had when its state was captured.

    A state is captured from an env that was reset (``has_reset``; stepping one
    that was not raises in gymnasium, which kills a batched env's worker), and the
    ``TimeLimit`` counter is -1 (unset) or a count.

    Example:
        >>> check_wrappers(3, True)
        >>> try:
        ...     check_wrappers(3, False)
        ... except StateCorruptedError as err:
        ...     print(err)
        wrappers.has_reset is False: the state of an env that was never reset
    """
    if elapsed_steps < -1:
        raise StateCorruptedError(f"{where}.elapsed_steps is {elapsed_steps}, not -1 or a count")
    if not has_reset:
        raise StateCorruptedError(
            f"{where}.has_reset is False: the state of an env that was never reset"
        )


def restore_wrappers(env: gym.Env, elapsed_steps: int, has_reset: bool) -> None:
    """Write wrapper counters back (the inverse of :func:`encode_wrappers`)."""
    for wrapper in _wrappers(env):
        if isinstance(wrapper, gym.wrappers.TimeLimit):
            wrapper._elapsed_steps = None if elapsed_steps < 0 else int(elapsed_steps)
        elif isinstance(wrapper, gym.wrappers.OrderEnforcing):
            wrapper._has_reset = bool(has_reset)


def time_limit(env: gym.Env) -> int | None:
    """The ``TimeLimit`` wrapper's limit of ``env``, or ``None``.

    Example:
        >>> time_limit(gym.make("CartPole-v1"))
        500
    """
    for wrapper in _wrappers(env):
        if isinstance(wrapper, gym.wrappers.TimeLimit):
            return wrapper._max_episode_steps
    return None


def _wrappers(env: gym.Env):
    while isinstance(env, gym.Wrapper):
        yield env
        env = env.env
