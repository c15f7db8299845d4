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
from tensordict import TensorDictBase
from torchrl.data import Composite

from torchrl_grpo.envs.core.bits import check_state_layout


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
