"""Which state codec serves which gymnasium env id."""

from __future__ import annotations

from collections.abc import Callable

from torchrl_grpo.envs.cartpole_codec import CartPoleStateCodec
from torchrl_grpo.envs.codec import StateCodec
from torchrl_grpo.envs.highway_codec import HighwayStateCodec

HIGHWAY_SCENARIOS: tuple[str, ...] = (
    "highway-v0",
    "highway-fast-v0",
    "merge-v0",
    "roundabout-v0",
    "intersection-v0",
    "racetrack-v0",
    "parking-v0",
    "exit-v0",
    "u-turn-v0",
    "two-way-v0",
    "lane-keeping-v0",
)

_CODECS: dict[str, Callable[[], StateCodec]] = {
    "CartPole-v1": CartPoleStateCodec,
    **{scenario: HighwayStateCodec for scenario in HIGHWAY_SCENARIOS},
}


def register_codec(env_id: str, factory: Callable[[], StateCodec]) -> None:
    """Make ``SnapshotEnv(env_id)`` use codecs built by ``factory``.

    Args:
        env_id: a gymnasium env id.
        factory: a callable returning a fresh, unbound codec.

    Example:
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
