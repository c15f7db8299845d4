"""Compatibility: the codec interface and the bit helpers moved to :mod:`torchrl_grpo.envs.core`.

``from torchrl_grpo.envs.codec import from_bits`` (as the CartPole tutorial once wrote)
keeps working; new code imports these names from :mod:`torchrl_grpo.envs`.
"""

from torchrl_grpo.envs.core.bits import (  # noqa: F401 - re-exported
    check_state_layout,
    from_bits,
    state_differences,
    states_equal,
    to_bits,
)
from torchrl_grpo.envs.core.codec import StateCodec, stable_hash  # noqa: F401 - re-exported

__all__ = [
    "StateCodec",
    "check_state_layout",
    "from_bits",
    "stable_hash",
    "state_differences",
    "states_equal",
    "to_bits",
]
