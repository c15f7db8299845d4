"""TorchRL environments whose complete simulator state is a TensorDict of tensors."""

from torchrl_grpo.envs.cartpole import CartPoleStateCodec
from torchrl_grpo.envs.core.actions import InvalidActionError
from torchrl_grpo.envs.core.batched import (
    SnapshotParallelEnv,
    SnapshotSerialEnv,
    check_worker_states,
    local_worker_env,
)
from torchrl_grpo.envs.core.bits import (
    check_state_layout,
    from_bits,
    state_differences,
    states_equal,
    to_bits,
)
from torchrl_grpo.envs.core.codec import StateCodec, stable_hash
from torchrl_grpo.envs.core.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    StateMismatchError,
    UnknownFieldError,
)
from torchrl_grpo.envs.core.registry import codec_for, register_codec
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY, SnapshotEnv
from torchrl_grpo.envs.highway import (
    HIGHWAY_SCENARIOS,
    TENSOR_SCENARIOS,
    HighwayEnv,
    HighwayStateCodec,
    TensorHighwayEnv,
    check_tensor_config,
    tensor_params,
)
from torchrl_grpo.envs.highway.schema import (
    Field,
    register_class_parameter,
    register_vehicle_class,
)

__all__ = [
    "HIGHWAY_SCENARIOS",
    "STATE_KEY",
    "TENSOR_SCENARIOS",
    "CartPoleStateCodec",
    "Field",
    "HighwayEnv",
    "HighwayStateCodec",
    "InvalidActionError",
    "SnapshotEnv",
    "SnapshotError",
    "SnapshotParallelEnv",
    "SnapshotSerialEnv",
    "StateCapacityError",
    "StateCodec",
    "StateCorruptedError",
    "StateMismatchError",
    "TensorHighwayEnv",
    "UnknownFieldError",
    "check_state_layout",
    "check_tensor_config",
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
    "tensor_params",
    "to_bits",
]
