"""A counter-based random stream per world: reproducible, branchable, tensors only.

A world's stream is two int64 words, its ``key`` and its ``counter``. Draw ``k`` of
a call is a hash of (key, counter, k), so a world's draws do not depend on the other
rows of the batch, on the device or on the batch size, and copying the two words
copies the stream (a snapshot is a clone). Each call advances the counter by one.

The hash is SplitMix64's finaliser applied twice, with the key mixed in between: a
well-tested 64-bit mixer that needs only int64 multiplies, xors and shifts. torch's
int64 arithmetic wraps modulo 2^64 on CPU and CUDA, which is what the mixer needs;
right shifts are arithmetic on int64, so they are masked back to logical shifts.

Example:
    >>> import torch
    >>> key, counter = seed_keys(torch.tensor([0, 1]), seed=7), torch.zeros(2, dtype=torch.int64)
    >>> u, counter = uniform(key, counter, 3)
    >>> u.shape, bool(((u >= 0) & (u < 1)).all()), counter.tolist()
    (torch.Size([2, 3]), True, [1, 1])
    >>> torch.equal(uniform(key, torch.zeros(2, dtype=torch.int64), 3)[0], u)
    True
"""

from __future__ import annotations

import torch

__all__ = ["DRAWS_PER_CALL", "mix64", "seed_keys", "uniform"]

# Constants of SplitMix64 (Steele, Lea and Flood, 2014) as signed int64.
_GOLDEN = -7046029254386353131  # 0x9E3779B97F4A7C15
_M1 = -4658895280553007687  # 0xBF58476D1CE4E5B9
_M2 = -7723592293110705685  # 0x94D049BB133111EB

#: Draw indices one call may use: a call's counter reserves this many.
DRAWS_PER_CALL = 1 << 20


def _shift_right(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 words."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def mix64(x: torch.Tensor) -> torch.Tensor:
    """SplitMix64's finaliser: a bijection of int64 words that scatters every bit.

    Args:
        x: int64 words.

    Returns:
        int64 words of the same shape.

    Example:
        >>> mix64(torch.tensor([0, 1])).tolist()
        [0, 6238072747940578789]
    """
    x = (x ^ _shift_right(x, 30)) * _M1
    x = (x ^ _shift_right(x, 27)) * _M2
    return x ^ _shift_right(x, 31)


def seed_keys(rows: torch.Tensor, seed: int) -> torch.Tensor:
    """The stream keys of ``rows`` of a batch seeded with ``seed``.

    Args:
        rows: int64 row indices (or any per-world integers).
        seed: the batch's seed.

    Returns:
        int64 keys, one per row, all different for different rows.

    Example:
        >>> seed_keys(torch.arange(3), seed=0).unique().numel()
        3
    """
    base = mix64(torch.tensor(int(seed), dtype=torch.int64, device=rows.device) * _GOLDEN + 1)
    return mix64(base + rows.to(torch.int64) * _GOLDEN)


def uniform(
    key: torch.Tensor, counter: torch.Tensor, n: int, dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` uniform draws in [0, 1) per world, and the advanced counters.

    Args:
        key: int64 ``[B]`` stream keys.
        counter: int64 ``[B]`` counters.
        n: draws per world (at most :data:`DRAWS_PER_CALL`).
        dtype: floating dtype of the draws (53 random bits in float64).

    Returns:
        ``([B, n] draws, [B] counter + 1)``.

    Example:
        >>> k = seed_keys(torch.arange(4), 0)
        >>> u, _ = uniform(k, torch.zeros(4, dtype=torch.int64), 1000)
        >>> abs(float(u.mean()) - 0.5) < 0.02
        True
    """
    if not 0 < n <= DRAWS_PER_CALL:
        raise ValueError(f"uniform draws n={n}: expected 1 to {DRAWS_PER_CALL}")
    index = torch.arange(n, dtype=torch.int64, device=key.device)
    words = (counter.unsqueeze(-1) * DRAWS_PER_CALL + index) * _GOLDEN
    words = mix64(mix64(words + key.unsqueeze(-1)) ^ key.unsqueeze(-1))
    draws = _shift_right(words, 11).to(torch.float64) * (2.0**-53)
    return draws.to(dtype), counter + 1
