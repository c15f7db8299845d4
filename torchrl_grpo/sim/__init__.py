"""A batched highway-env simulator in pure tensors: B worlds stepped at once, on CPU or GPU.

This package re-implements highway-env 1.12.1's highway scenarios (``highway-v0``,
``highway-fast-v0``) and ``merge-v0`` as pure functions of batched tensors, in the style
of TorchRL's ``envs/custom/pendulum.py`` and Brax: the state (:class:`World`, or its TensorDict
form), the road and the constants (:class:`HighwayParams`) go in, the new state comes
out. It imports only torch and tensordict; the TorchRL env around it
(``TensorHighwayEnv``) and the bridge to highway-env's own states live in
:mod:`torchrl_grpo.envs.highway`.

One file per model: :mod:`.road` (lane geometry), :mod:`.neighbours` (front and rear
vehicles from one sort per substep), :mod:`.idm`, :mod:`.mobil`, :mod:`.control` (the
steering and speed controllers, the ego's meta-actions), :mod:`.kinematics`,
:mod:`.collision`, :mod:`.observation`, :mod:`.reward`, :mod:`.reset`, composed by
:mod:`.simulate`; merge-v0 adds :mod:`.lanes` (straight, sine and circular lanes of a
road graph), :mod:`.merge` (its step), :mod:`.merge_reset`, :mod:`.merge_output` and
:mod:`.merge_params`; :mod:`.state` holds the state's layout and checks, :mod:`.rng` the
per-world random streams, :mod:`.params` the constants. docs/sim.md describes the
parity with highway-env, measured step by step.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> params = tensor_params("highway-fast-v0")
    >>> world = empty_world(1024, params.num_vehicles)
    >>> world = reset_world(world._replace(rng_key=seed_keys(torch.arange(1024), 0)),
    ...                     torch.ones(1024, dtype=torch.bool), params)
    >>> snapshot = world_to_tensordict(world).clone()  # a snapshot is a clone
    >>> world, out = step(world, torch.full((1024,), 3), params)  # everyone: FASTER
    >>> out["reward"].shape
    torch.Size([1024])
"""

from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.reset import reset_world
from torchrl_grpo.sim.rng import seed_keys
from torchrl_grpo.sim.simulate import observe_world, step
from torchrl_grpo.sim.state import (
    World,
    check_world,
    empty_world,
    world_from_tensordict,
    world_to_tensordict,
)

__all__ = [
    "HighwayParams",
    "World",
    "check_world",
    "empty_world",
    "observe_world",
    "reset_world",
    "seed_keys",
    "step",
    "world_from_tensordict",
    "world_to_tensordict",
]
