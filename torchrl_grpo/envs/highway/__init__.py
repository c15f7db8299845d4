"""highway-env in TorchRL: HighwayEnv (highway-env itself, exact snapshots) and its codec.

:class:`~torchrl_grpo.envs.HighwayEnv` wraps every highway-env scenario with a state
that :class:`~torchrl_grpo.envs.HighwayStateCodec` writes into tensors; the codec's
field vocabulary and class registry are in :mod:`.schema`, its packed entity tables in
:mod:`.layout`. The public names are exported by :mod:`torchrl_grpo.envs`.
"""

from torchrl_grpo.envs.highway.codec import HIGHWAY_SCENARIOS, HighwayStateCodec
from torchrl_grpo.envs.highway.tensor_env import TensorHighwayEnv
from torchrl_grpo.envs.highway.tensor_params import (
    TENSOR_SCENARIOS,
    check_tensor_config,
    tensor_params,
)
from torchrl_grpo.envs.highway.wrapper import HighwayEnv

__all__ = [
    "HIGHWAY_SCENARIOS",
    "TENSOR_SCENARIOS",
    "HighwayEnv",
    "HighwayStateCodec",
    "TensorHighwayEnv",
    "check_tensor_config",
    "tensor_params",
]
