"""What every snapshotted simulator shares: the snapshot env, the codec interface, errors.

:class:`~torchrl_grpo.envs.SnapshotEnv` wraps a gymnasium env whose state a
:class:`~torchrl_grpo.envs.StateCodec` writes into tensors and reads back; the codec
registry finds a codec by env id; batched envs route states to their workers. The
simulators live beside this package (``envs/highway``, ``envs/cartpole.py``) and import
from it, never the other way. The public names are exported by :mod:`torchrl_grpo.envs`.
"""
