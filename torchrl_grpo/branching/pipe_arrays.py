"""What crosses a branch worker's pipe: numpy arrays by tuple key, and steps that keep state.

The parent of a :class:`~torchrl_grpo.branching.BranchParallelEnv` sends its workers
branch start states (:mod:`~torchrl_grpo.branching.worker_branches`), and a worker
answers with a branch's rows (:mod:`~torchrl_grpo.branching.branch_runner`), as numpy
arrays: the pipe pickles them in microseconds, where torch tensors would each be moved
to shared memory by torch's multiprocessing reductions. A worker encodes its state
only when the rollout keeps it (:func:`step_keeping_state`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_grpo.branching.keys import STATE

__all__ = [
    "STATE_ALWAYS",
    "STATE_AT_END",
    "STATE_NEVER",
    "from_arrays",
    "step_keeping_state",
    "to_arrays",
]

# When a worker reads the state after a step (and sends it back).
STATE_NEVER, STATE_ALWAYS, STATE_AT_END = 0, 1, 2

Arrays = dict[tuple[str, ...], np.ndarray]


def to_arrays(td: TensorDictBase, keys: Sequence[NestedKey] | None = None) -> Arrays:
    """The leaves of ``td`` (or its ``keys``) as numpy arrays, by tuple key.

    Example:
        >>> to_arrays(TensorDict(a=torch.ones(2), b={"c": torch.zeros(1)}))
        {('a',): array([1., 1.], dtype=float32), ('b', 'c'): array([0.], dtype=float32)}
    """
    if keys is None:
        keys = td.keys(True, True)
    return {_as_tuple(k): td.get(k).numpy() for k in keys}


def from_arrays(arrays: Sequence[Arrays], batch: bool = True) -> TensorDict:
    """Stack the ``arrays`` of several jobs into one tensordict (``[len(arrays)]``).

    With ``batch=False``, ``arrays`` holds one entry and the tensordict is unbatched.

    Example:
        >>> row = to_arrays(TensorDict(a=torch.ones(2)))
        >>> from_arrays([row, row]).batch_size
        torch.Size([2])
    """
    out = TensorDict(batch_size=[len(arrays)] if batch else [])
    for key in arrays[0]:
        if batch:
            value = torch.from_numpy(np.stack([a[key] for a in arrays]))
        else:
            value = torch.from_numpy(arrays[0][key].copy())
        out.set(key, value)
    return out


def step_keeping_state(
    env: EnvBase, td: TensorDictBase, mode: int, last: bool
) -> tuple[TensorDictBase, TensorDictBase | None]:
    """Step ``env`` with the action in ``td``; return the step's ``"next"`` and the state.

    The state after the step is read when ``mode`` asks for it: ``STATE_ALWAYS``, or
    ``STATE_AT_END`` on the branch's ``last`` step or one that ends it; otherwise
    ``None`` (and an env built with ``return_state=True`` skips encoding it).

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = HighwayEnv("merge-v0", return_state=True)
        >>> _ = env.reset()
        >>> nxt, state = step_keeping_state(env, TensorDict(action=torch.tensor(1)),
        ...                                 STATE_AT_END, last=False)
        >>> STATE in nxt.keys(), state is None
        (False, True)
    """
    base = _base(env)
    returns_state = getattr(base, "return_state", None) is True
    if returns_state and mode != STATE_ALWAYS:
        # The state is encoded only when it is sent back (it costs up to a third
        # of a merge-v0 step); read after the step, it is what the step would write.
        base.return_state = False
        try:
            nxt = env.step(td).get("next")
        finally:
            base.return_state = True
    else:
        nxt = env.step(td).get("next")
    snap = None
    if mode == STATE_ALWAYS or (mode == STATE_AT_END and (last or bool(nxt.get("done").any()))):
        snap = nxt.get(STATE) if STATE in nxt.keys() else env.get_state()
    return nxt, snap


def _base(env: EnvBase) -> EnvBase:
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return key if isinstance(key, tuple) else (key,)
