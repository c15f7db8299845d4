"""TorchRL environments whose complete simulator state is a TensorDict of tensors."""

from torchrl_grpo.envs.cartpole import CartPoleStateCodec
from torchrl_grpo.envs.core.action_validation import InvalidActionError
from torchrl_grpo.envs.core.bits import from_bits, state_differences, states_equal, to_bits
from torchrl_grpo.envs.core.codec_registry import register_codec
from torchrl_grpo.envs.core.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    StateMismatchError,
    UnknownFieldError,
)
from torchrl_grpo.envs.core.snapshot_batched import SnapshotParallelEnv, SnapshotSerialEnv
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY, SnapshotEnv
from torchrl_grpo.envs.core.state_codec import StateCodec
from torchrl_grpo.envs.highway.highway_codec import HIGHWAY_SCENARIOS
from torchrl_grpo.envs.highway.schema import Field, register_class_parameter, register_vehicle_class
from torchrl_grpo.envs.highway.tensor_env import TensorHighwayEnv
from torchrl_grpo.envs.highway.tensor_params import TENSOR_SCENARIOS, tensor_params
from torchrl_grpo.envs.highway.wrapper import HighwayEnv

__all__ = [
    "HIGHWAY_SCENARIOS",
    "STATE_KEY",
    "TENSOR_SCENARIOS",
    "CartPoleStateCodec",
    "Field",
    "HighwayEnv",
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
    "from_bits",
    "register_class_parameter",
    "register_codec",
    "register_vehicle_class",
    "state_differences",
    "states_equal",
    "tensor_params",
    "to_bits",
]
