"""Branch lanes: the part of a branch worker that runs jobs sent through its pipe.

A :class:`~torchrl_grpo.branching.BranchParallelEnv` worker holds ``lanes`` envs built
by the same constructor: its TorchRL env and ``lanes - 1`` more, built at the first job
that needs them. The parent sends a worker one job per message (restore lane ``j`` to
a state, or step lane ``j`` with an action) and may queue several before it reads the
answers, so that a worker steps one lane while the parent runs the policy for another.

Jobs reach the worker through TorchRL's generic attribute call (the worker calls
``env.branch_jobs(*args)`` and answers ``("branch_jobs_done", result)``), which is why
:class:`~torchrl_grpo.branching.worker_factory.BranchWorkerFactory` attaches a
:class:`LaneRunner` to each worker env. Results
travel as numpy arrays: the pipe pickles them in microseconds, where torch tensors
would each be moved to shared memory by torch's multiprocessing reductions.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_grpo.branching.keys import STATE

__all__ = ["LaneRunner", "from_arrays", "step_keeping_state", "to_arrays"]

# State modes of a step job: when to send the state after the step back.
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


class LaneRunner:
    """Runs branch jobs on the lanes of one worker (lane 0 is the worker's env).

    Args:
        env: the worker's env.
        make: builds one more env like ``env`` (for the lanes past the first).

    Example:
        >>> import functools
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> make = functools.partial(HighwayEnv, "merge-v0", return_state=True)
        >>> env = make()
        >>> runner = LaneRunner(env, make)
        >>> state = to_arrays(env.reset().get("state"))
        >>> keys = [("observation",), ("done",)]
        >>> out = runner([("restore", 1, state, False), ("step", 1, {("action",): np.array(1)},
        ...               STATE_AT_END, True)], keys, keys)
        >>> sorted(out[1]["out"]), out[1]["state"] is not None
        ([('done',), ('observation',)], True)
    """

    def __init__(self, env: EnvBase, make: Callable[[], EnvBase]) -> None:
        self.lanes = [env]
        self.make = make

    def lane(self, index: int) -> EnvBase:
        """The env of lane ``index``, built on first use."""
        while len(self.lanes) <= index:
            self.lanes.append(self.make())
        return self.lanes[index]

    def __call__(
        self, jobs: Sequence[tuple], reset_keys: Sequence[NestedKey], step_keys: Sequence[NestedKey]
    ) -> list[dict[str, Any]] | tuple[str, str]:
        """Run ``jobs`` in order; return one ``{"out", "state"}`` per job, or an error.

        A job is ``("restore", lane, state, want_state)`` or ``("step", lane, action,
        state_mode, last)``; ``reset_keys`` / ``step_keys`` name the entries of the
        reset output / of the step's ``"next"`` to send back. An exception is returned
        as ``("error", traceback)``: the worker stays alive and the parent raises it.
        """
        try:
            return [self._run(job, reset_keys, step_keys) for job in jobs]
        except Exception:
            return ("error", traceback.format_exc())

    def _run(
        self, job: tuple, reset_keys: Sequence[NestedKey], step_keys: Sequence[NestedKey]
    ) -> dict[str, Any]:
        kind, lane = job[0], job[1]
        env = self.lane(lane)
        if kind == "restore":
            state = from_arrays([job[2]], batch=False)
            out = env.reset(TensorDict({STATE: state}), set_state=True)
            snap = to_arrays(out.get(STATE)) if job[3] else None
            return {"out": to_arrays(out, reset_keys), "state": snap}
        _, _, action, mode, last = job
        nxt, snap = step_keeping_state(env, from_arrays([action], batch=False), mode, last)
        return {
            "out": to_arrays(nxt, step_keys),
            "state": None if snap is None else to_arrays(snap),
        }


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
