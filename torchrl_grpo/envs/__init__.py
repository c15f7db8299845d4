"""TorchRL environments whose complete simulator state is a TensorDict of tensors."""

from torchrl_grpo.envs.batched import (
    SnapshotParallelEnv,
    SnapshotSerialEnv,
    check_worker_states,
    local_worker_env,
)
from torchrl_grpo.envs.cartpole_codec import CartPoleStateCodec
from torchrl_grpo.envs.codec import (
    StateCodec,
    check_state_layout,
    from_bits,
    stable_hash,
    state_differences,
    states_equal,
    to_bits,
)
from torchrl_grpo.envs.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    StateMismatchError,
    UnknownFieldError,
)
from torchrl_grpo.envs.highway import HighwayEnv
from torchrl_grpo.envs.highway_codec import HighwayStateCodec
from torchrl_grpo.envs.highway_schema import (
    Field,
    register_class_parameter,
    register_vehicle_class,
)
from torchrl_grpo.envs.registry import HIGHWAY_SCENARIOS, codec_for, register_codec
from torchrl_grpo.envs.snapshot_env import STATE_KEY, SnapshotEnv

__all__ = [
    "HIGHWAY_SCENARIOS",
    "STATE_KEY",
    "CartPoleStateCodec",
    "Field",
    "HighwayEnv",
    "HighwayStateCodec",
    "SnapshotEnv",
    "SnapshotError",
    "SnapshotParallelEnv",
    "SnapshotSerialEnv",
    "StateCapacityError",
    "StateCodec",
    "StateCorruptedError",
    "StateMismatchError",
    "UnknownFieldError",
    "check_state_layout",
    "check_worker_states",
    "codec_for",
    "from_bits",
    "local_worker_env",
    "register_class_parameter",
    "register_codec",
    "register_vehicle_class",
    "stable_hash",
    "state_differences",
    "states_equal",
    "to_bits",
]
