"""A state codec for gymnasium's CartPole-v1: the smallest complete example of a codec."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.core.bits import check_state_layout
from torchrl_grpo.envs.core.codec_registry import register_codec
from torchrl_grpo.envs.core.errors import StateCorruptedError
from torchrl_grpo.envs.core.gym_state import (
    check_wrappers,
    decode_rng,
    encode_rng,
    encode_wrappers,
    restore_wrappers,
    rng_spec,
    with_seeded_rng,
    wrapper_spec,
)
from torchrl_grpo.envs.core.state_codec import StateCodec

__all__ = ["CartPoleStateCodec"]


class CartPoleStateCodec(StateCodec):
    """Snapshot of ``CartPole-v1``.

    It holds the 4 physical variables, the termination counter, the RNG and the
    wrappers' counters.

    Example:
        >>> from torchrl_grpo.envs import SnapshotEnv
        >>> env = SnapshotEnv("CartPole-v1", codec=CartPoleStateCodec(), seed=0)
        >>> state = env.get_state()
        >>> state["sim", "physics"].shape
        torch.Size([4])
    """

    def state_spec(self) -> Composite:
        """See :meth:`StateCodec.state_spec`."""
        return Composite(
            # x, x_dot, theta, theta_dot as float64 bit patterns (see codec.FLOAT_BITS).
            physics=Unbounded((4,), dtype=torch.int64),
            # gymnasium counts steps taken after termination (None before): -1 encodes None.
            steps_beyond_terminated=Unbounded((), dtype=torch.int64),
            rng=rng_spec(),
            wrappers=wrapper_spec(),
        )

    def encode(self, env: gym.Env) -> TensorDictBase:
        """See :meth:`StateCodec.encode`."""
        core = env.unwrapped
        rng = np.zeros(10, dtype=np.int64)
        encode_rng(core.np_random, rng)
        beyond = core.steps_beyond_terminated
        return TensorDict(
            physics=torch.from_numpy(np.array(core.state, dtype=np.float64).view(np.int64)),
            steps_beyond_terminated=torch.tensor(-1 if beyond is None else beyond),
            rng=torch.from_numpy(rng),
            wrappers=TensorDict({k: torch.from_numpy(v) for k, v in encode_wrappers(env).items()}),
        )

    def validate(self, env: gym.Env, state: TensorDictBase) -> None:
        """See :meth:`StateCodec.validate`."""
        self._prepare(state)

    def reseed(self, state: TensorDictBase, seed: int) -> TensorDictBase:
        """See :meth:`StateCodec.reseed`: replaces the ``"rng"`` words."""
        return with_seeded_rng(state, "rng", seed)

    def decode(self, env: gym.Env, state: TensorDictBase) -> None:
        """See :meth:`StateCodec.decode`."""
        physics, rng_state, beyond = self._prepare(state)
        # Everything is validated: only now is the env modified.
        core = env.unwrapped
        core.state = physics
        core.steps_beyond_terminated = None if beyond < 0 else beyond
        core.np_random.bit_generator.state = rng_state
        restore_wrappers(
            env, int(state["wrappers", "elapsed_steps"]), bool(state["wrappers", "has_reset"])
        )

    def _prepare(self, state: TensorDictBase) -> tuple[np.ndarray, dict, int]:
        check_state_layout(state, self.state_spec())
        physics = state["physics"].numpy().view(np.float64).copy()
        if not np.isfinite(physics).all():
            raise StateCorruptedError(f"CartPole physics holds non-finite values: {physics}")
        rng_state = decode_rng(state["rng"].numpy())
        check_wrappers(
            int(state["wrappers", "elapsed_steps"]), bool(state["wrappers", "has_reset"])
        )
        beyond = int(state["steps_beyond_terminated"])
        return physics, rng_state, beyond


register_codec("CartPole-v1", CartPoleStateCodec)
