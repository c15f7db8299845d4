"""Give each branch its own simulator random stream.

highway-env draws almost no random numbers after a reset, so branches restored from
one state differ only through the policy's samples. intersection-v0 is the
exception: it spawns traffic from the env's generator at every step. Reseeding a
branch's state (``rng="per_branch"`` in the rollout functions) makes its traffic its
own, at the price of branches that no longer share their future traffic.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDictBase

from torchrl_grpo.envs.gym_state import RNG_WORDS, encode_rng

# Where the highway and CartPole codecs keep the PCG64 words of env.np_random.
# TODO(lead): replace with a public reseed hook of torchrl_grpo.envs when there is one.
RNG_KEY = ("sim", "env", "rng")

__all__ = ["RNG_KEY", "reseed_state"]


def reseed_state(state: TensorDictBase, seed: int | Sequence[int]) -> TensorDictBase:
    """Return a copy of ``state`` whose simulator generator restarts from ``seed``.

    Only the generator words change: vehicles, time and counters are untouched, so
    the restored simulator is the same scene with a fresh random stream (the stream
    ``numpy.random.default_rng(seed)`` would give).

    Args:
        state: an unbatched state from :meth:`~torchrl_grpo.envs.SnapshotEnv.get_state`.
        seed: an int, or a sequence of ints mixed by numpy's ``SeedSequence``
            (e.g. ``(base_seed, group_id, branch)``).

    Returns:
        A new state (the input is not modified).

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv, states_equal
        >>> state = HighwayEnv("intersection-v0", seed=0).get_state()
        >>> a, b = reseed_state(state, 1), reseed_state(state, 2)
        >>> states_equal(a, reseed_state(state, 1)), states_equal(a, b)
        (True, False)
    """
    if RNG_KEY not in state.keys(True, True):
        raise KeyError(
            f"this state has no {RNG_KEY!r} entry: its codec does not store a PCG64 "
            "generator there, so it cannot be reseeded"
        )
    if state.batch_dims:
        raise ValueError(f"reseed_state takes one state, got batch size {tuple(state.batch_size)}")
    words = np.zeros(RNG_WORDS, dtype=np.int64)
    encode_rng(np.random.default_rng(seed if isinstance(seed, int) else list(seed)), words)
    out = state.clone()
    out.set(RNG_KEY, torch.from_numpy(words))
    return out
