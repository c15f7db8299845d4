"""Which state codec serves which gymnasium env id.

Each simulator package registers its codecs when it is imported (``torchrl_grpo.envs``
imports them all), so that :class:`~torchrl_grpo.envs.SnapshotEnv` finds them by env id.
"""

from __future__ import annotations

from collections.abc import Callable

from torchrl_grpo.envs.core.state_codec import StateCodec

# Filled by the simulator packages as they are imported (torchrl_grpo.envs imports them
# all): core does not import the simulators it serves.
_CODECS: dict[str, Callable[[], StateCodec]] = {}


def register_codec(env_id: str, factory: Callable[[], StateCodec]) -> None:
    """Make ``SnapshotEnv(env_id)`` use codecs built by ``factory``.

    Args:
        env_id: a gymnasium env id.
        factory: a callable returning a fresh, unbound codec.

    Example:
        >>> from torchrl_grpo.envs import CartPoleStateCodec
        >>> register_codec("CartPole-v0", CartPoleStateCodec)
        >>> type(codec_for("CartPole-v0")).__name__
        'CartPoleStateCodec'
    """
    _CODECS[env_id] = factory


def codec_for(env_id: str) -> StateCodec:
    """A fresh codec for ``env_id``.

    Raises:
        KeyError: no codec is registered for it (the message lists those that are).

    Example:
        >>> type(codec_for("merge-v0")).__name__
        'HighwayStateCodec'
    """
    try:
        return _CODECS[env_id]()
    except KeyError:
        raise KeyError(
            f"no state codec is registered for {env_id!r}; known: {sorted(_CODECS)}. "
            "Pass codec=... or call torchrl_grpo.envs.register_codec."
        ) from None
