"""Batched envs of snapshot envs that check every state before any worker restores one.

TorchRL's ``SerialEnv`` and ``ParallelEnv`` hand each worker its slice of the reset
tensordict. A state that a worker refuses then does damage the error cannot undo: a
``ParallelEnv`` worker that raises dies (the caller gets ``"Cannot proceed, worker 0
dead"`` and the env is unusable), and a ``SerialEnv`` has already restored the workers
before the one that refused. :class:`SnapshotSerialEnv` and
:class:`SnapshotParallelEnv` run every worker's checks
(:meth:`~torchrl_grpo.envs.SnapshotEnv.validate_state`) in this process first, so a
bad state raises the error that names the problem and leaves every worker as it was.
"""

from __future__ import annotations

import weakref
from typing import Any

from tensordict import TensorDictBase, unravel_key
from torchrl.data import Composite
from torchrl.envs import EnvBase, ParallelEnv, SerialEnv, TransformedEnv

from torchrl_grpo.envs.core.action_validation import check_action
from torchrl_grpo.envs.core.errors import SnapshotError
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY

__all__ = [
    "SnapshotParallelEnv",
    "SnapshotSerialEnv",
    "check_worker_states",
    "local_worker_env",
]


def _base(env: EnvBase) -> EnvBase:
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env


# Per batched env, the local copies of its workers, for as long as the batched env lives:
# building one costs a gym.make and a reset (~0.2 s for highway-fast-v0).
_LOCAL_WORKERS: weakref.WeakKeyDictionary[EnvBase, dict[int, EnvBase]] = weakref.WeakKeyDictionary()


def local_worker_env(env: EnvBase, worker: int = 0) -> EnvBase:
    """An untransformed env in this process built like worker ``worker`` of ``env``.

    For a plain env, the env itself (transforms removed); for a ``SerialEnv``, its
    worker; for a ``ParallelEnv``, a local instance built with the worker's
    constructor and arguments, cached for as long as ``env`` lives (workers built
    by one constructor share one). Use it for what needs the workers' codec in the
    parent: checking and reseeding states.

    Args:
        env: a plain or batched env, optionally transformed.
        worker: the worker whose construction to copy.

    Returns:
        The env (its untransformed base env).

    Example:
        >>> import functools
        >>> from torchrl.envs import SerialEnv
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = SerialEnv(2, functools.partial(HighwayEnv, "merge-v0"))
        >>> type(local_worker_env(env, 1)).__name__
        'HighwayEnv'
        >>> env.close()
    """
    batched = _base(env)
    if not isinstance(batched, (SerialEnv, ParallelEnv)):
        return batched
    if not 0 <= worker < batched.num_workers:
        raise IndexError(f"worker {worker} of an env with {batched.num_workers} workers")
    if isinstance(batched, SerialEnv):
        if batched.is_closed:
            batched.start()
        return _base(batched._envs[worker])
    # Read the instance dict: ParallelEnv.__getattr__ forwards unknown attributes.
    built = 0 if batched.__dict__.get("_single_task", False) else worker
    cache = _LOCAL_WORKERS.setdefault(batched, {})
    if built not in cache:
        make = batched.create_env_fn[built]
        cache[built] = _base(make(**(batched.create_env_kwargs[built] or {})))
    return cache[built]


def check_worker_states(env: EnvBase, tensordict: TensorDictBase) -> None:
    """Run the restore checks of every worker that ``tensordict`` would restore.

    The workers are those of the ``"_reset"`` mask, or all of them when there is
    none; each state is checked by a local copy of its worker
    (:func:`local_worker_env`). Workers that are not snapshot envs (no
    ``validate_state``) are not checked.

    Args:
        env: a ``SerialEnv`` or ``ParallelEnv`` of snapshot envs.
        tensordict: the reset input, batch ``[W]``, with its states under ``"state"``.

    Raises:
        SnapshotError: the first state that would be refused, naming its worker.

    Example:
        >>> import functools
        >>> from tensordict import TensorDict
        >>> from torchrl.envs import SerialEnv
        >>> from torchrl_grpo.envs import HighwayEnv, StateMismatchError
        >>> env = SerialEnv(2, functools.partial(HighwayEnv, "merge-v0"))
        >>> other = HighwayEnv("highway-fast-v0").get_state()
        >>> try:
        ...     check_worker_states(env, TensorDict(state=other.expand(2), batch_size=[2]))
        ... except StateMismatchError as err:
        ...     print("refused")
        refused
        >>> env.close()
    """
    states = tensordict.get(STATE_KEY, None)
    if states is None:
        return
    batched = _base(env)
    num_workers = batched.num_workers
    mask = tensordict.get("_reset", None)
    if mask is None:
        workers: list[int] = list(range(num_workers))
    else:
        workers = mask.reshape(num_workers, -1).any(-1).nonzero().flatten().tolist()
    for worker in workers:
        local = local_worker_env(batched, worker)
        validate = getattr(local, "validate_state", None)
        if validate is None:
            continue
        try:
            validate(states[worker])
        except SnapshotError as err:
            # Same class, so callers catch what a plain restore raises, plus the worker.
            raise type(err)(f"worker {worker}: {err}") from err


class _ChecksStatesFirst:
    """Mixin for ``SerialEnv`` / ``ParallelEnv``: check every state and action before any worker.

    A reset also returns the workers' states, as a single snapshot env's reset does:
    the state is in ``state_spec`` (it routes a restore to every worker), so an output
    without it would not match the specs (``check_env_specs``) unless the workers
    return it at every step (``return_state=True``).

    A step checks the whole batch of actions against the batched action spec first
    (``check_actions=False`` skips it): a ``SerialEnv`` would have stepped the workers
    before the one that refuses, and a ``ParallelEnv`` worker that refuses dies.
    """

    def __init__(self, *args: Any, check_actions: bool = True, **kwargs: Any) -> None:
        self.check_actions = check_actions
        super().__init__(*args, **kwargs)

    def _check_actions(self, tensordict: TensorDictBase) -> None:
        if not self.__dict__.get("check_actions", True):
            return
        spec = self.full_action_spec
        name = f"{type(self).__name__} of {self.batch_size[0]} workers"
        rows = tensordict.get("_step", None)
        for key in self.action_keys:
            check_action(
                tensordict.get(key, None),
                spec[key],
                name,
                batch_dims=len(self.batch_size),
                rows=rows,
            )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._check_actions(tensordict)
        return super()._step(tensordict)

    def _create_td(self) -> None:
        super()._create_td()
        if "_selected_reset_keys" not in self.__dict__:
            return  # no shared buffers: a reset returns the workers' outputs whole
        # Before the workers start: they receive the reset keys they write back.
        states = {
            unravel_key((STATE_KEY, key))
            for key in self.state_spec.get(STATE_KEY, Composite()).keys(True, True)
        }
        self._selected_reset_keys = self._selected_reset_keys | states
        self._selected_reset_keys_filt = self._selected_reset_keys_filt | states

    def _reset(self, tensordict: TensorDictBase | None, **kwargs: Any) -> TensorDictBase:
        if kwargs.get("set_state") and tensordict is not None:
            check_worker_states(self, tensordict)
        return super()._reset(tensordict, **kwargs)


class SnapshotSerialEnv(_ChecksStatesFirst, SerialEnv):
    """A ``SerialEnv`` whose ``reset(..., set_state=True)`` restores all workers or none.

    Every state is checked before the first worker restores, so a refused state
    leaves every worker as it was (a plain ``SerialEnv`` restores the workers before
    the one that refuses). Likewise every action before the first worker steps
    (:class:`~torchrl_grpo.envs.InvalidActionError`; ``check_actions=False`` skips it).

    Example:
        >>> import functools
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = SnapshotSerialEnv(2, functools.partial(HighwayEnv, "merge-v0", seed=0))
        >>> _ = env.reset()
        >>> states = torch.stack(env.get_state())
        >>> env.reset(TensorDict(state=states, batch_size=[2]), set_state=True).batch_size
        torch.Size([2])
        >>> env.close()
    """


class SnapshotParallelEnv(_ChecksStatesFirst, ParallelEnv):
    """A ``ParallelEnv`` that checks states and actions in this process before its workers see them.

    A worker of a plain ``ParallelEnv`` that refuses a state raises in its own
    process and dies. Here the checks run first, in the parent, on a local copy of
    the worker (built on the first restore: a gym.make and a reset), so a bad
    state raises the error that names it and every worker lives on unchanged. Actions
    are checked against the batched action spec before any worker sees them
    (:class:`~torchrl_grpo.envs.InvalidActionError`; ``check_actions=False`` skips it).

    Example:
        >>> import functools
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.envs import HighwayEnv, StateMismatchError
        >>> env = SnapshotParallelEnv(1, functools.partial(HighwayEnv, "merge-v0"),
        ...                           mp_start_method="fork")
        >>> other = HighwayEnv("highway-fast-v0").get_state().unsqueeze(0)
        >>> try:
        ...     env.reset(TensorDict(state=other, batch_size=[1]), set_state=True)
        ... except StateMismatchError:
        ...     print("refused")
        refused
        >>> env.rollout(2).batch_size  # the worker lives on
        torch.Size([1, 2])
        >>> env.close()
    """

    def step_and_maybe_reset(
        self, tensordict: TensorDictBase
    ) -> tuple[TensorDictBase, TensorDictBase]:
        """See ``ParallelEnv.step_and_maybe_reset``; actions are checked first.

        With shared buffers TorchRL sends the actions to the workers without ``_step``.
        """
        if self.__dict__.get("_use_buffers", False):
            self._check_actions(tensordict)
        return super().step_and_maybe_reset(tensordict)
