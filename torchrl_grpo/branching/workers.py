"""Worker envs for branch rollouts: builders, a parent that sleeps, clean shutdown.

Branch rollouts read every worker's state after each restore and step. Workers
built with ``HighwayEnv(..., return_state=True)`` declare ``"state"`` as an
observation, so a ``ParallelEnv`` returns it (``"state"`` after a reset,
``("next", "state")`` after a step) through its shared buffers: one shared-memory
copy instead of a pipe round trip per worker through ``penv.get_state()``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Sequence
from multiprocessing import connection
from typing import Any

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase, unravel_key
from torchrl.envs import EnvBase

from torchrl_grpo.branching.keys import STATE
from torchrl_grpo.branching.worker_factory import BranchWorkerFactory
from torchrl_grpo.envs.core.snapshot_batched import SnapshotParallelEnv

logger = logging.getLogger(__name__)


__all__ = ["BranchParallelEnv"]


class BranchParallelEnv(SnapshotParallelEnv):
    """A ``ParallelEnv`` whose parent process sleeps while its workers step.

    As a :class:`~torchrl_grpo.envs.SnapshotParallelEnv`, it checks states in the
    parent before a ``reset(..., set_state=True)`` sends them to its workers.

    TorchRL's ``ParallelEnv`` waits for its workers by spinning on shared-memory
    flags, which keeps one core busy in the parent. With W workers on W cores the
    workers then share W - 1 cores: on 2 cores, 2 workers ran no faster than 1 (the
    benchmark's ``W=2 spin`` row). This subclass polls the same flags with short
    sleeps (10 us to 2 ms, against steps of 10+ ms), leaving the cores to the workers.
    Each sleep costs the parent CPU (a wake-up, 15 to 50 us), so a wait of
    :meth:`branch_restore` / :meth:`branch_step` starts with one sleep of 60 % of the
    recent waits of its kind and then polls every 1/24th of them: about 10 wake-ups
    per step instead of 60+.

    Branch rollouts also restore and step workers through :meth:`branch_restore`
    and :meth:`branch_step`, which move only what a branch rollout reads between
    the parent and the workers: the actions and, on a restore, the state in; the
    observations, reward, done flags and (only when asked) the state out. TorchRL's
    ``reset`` and ``step`` walk every entry of the shared buffers, simulator states
    included, on every call, which cost the parent milliseconds per step.

    The overrides replace private parts: they are written against torchrl 0.14.1,
    whose ``ParallelEnv._wait_for_workers(workers_range)`` waits, in shared-buffer
    mode, until the byte ``_shm_done_flags[_worker_indices[i]]`` of every worker
    ``i`` is set, then clears them, and whose workers answer ``("step", {})`` and
    ``("reset", (keys, kwargs))`` by stepping or resetting from the shared buffers
    (``shared_tensordict_parent``). When those attributes are not there as expected
    (another TorchRL version, pipe mode with ``use_buffers=False``) or
    :attr:`sleep_while_waiting` is ``False``, TorchRL's own wait runs instead; when
    :meth:`branch_fast_paths_apply` is ``False``, branch rollouts use ``reset`` and
    ``step``.

    Attributes:
        sleep_while_waiting: set to ``False`` to use TorchRL's spinning wait.
        branch_fast_paths: set to ``False`` to make branch rollouts use TorchRL's
            ``reset`` and ``step``.
        whole_branches: run whole branches in the workers, each with its own copy of
            the policy (the default, see ``worker_branches``): the parent does nothing
            per step. ``False``, or a policy that does not pickle for CPU workers, runs
            the lock-step engine (the policy in the parent, see ``lockstep``).
        branch_queue_depth: whole branches queued per worker (2 by default: a worker
            starts its next branch without waiting for the parent to read its answer;
            in a rollout's last branches, 1, so that the workers finish together).

    Example:
        >>> import functools
        >>> from torchrl_grpo.branching import shutdown_env
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = BranchParallelEnv(1, functools.partial(HighwayEnv, "merge-v0"),
        ...                         mp_start_method="fork")
        >>> env.reset().batch_size
        torch.Size([1])
        >>> shutdown_env(env)
    """

    sleep_while_waiting: bool = True
    branch_fast_paths: bool = True
    whole_branches: bool = True
    branch_queue_depth: int = 2
    _MIN_SLEEP = 1e-5
    _MAX_SLEEP = 5e-4
    # Waits of branch_restore / branch_step: a first sleep of this share of the
    # recent waits of that kind (a moving average), then polls every 1/24th of it.
    _FIRST_SLEEP_SHARE = 0.6
    _POLLS_PER_WAIT = 24
    _MAX_POLL_SLEEP = 2e-3

    def __init__(
        self,
        num_workers: int,
        create_env_fn: Callable[..., EnvBase] | Sequence[Callable[..., EnvBase]],
        *args: Any,
        **kwargs: Any,
    ) -> None:
        # Each worker env gets a BranchRunner (env.branch_runs) for whole branches.
        if callable(create_env_fn):
            wrapped = _with_runner(create_env_fn)
        else:
            wrapped = [_with_runner(f) for f in create_env_fn]
        super().__init__(num_workers, wrapped, *args, **kwargs)

    def _sleeping_wait_applies(self) -> bool:
        # Read the instance dict: ParallelEnv.__getattr__ forwards unknown attributes
        # to the workers instead of raising AttributeError.
        d = self.__dict__
        flags = d.get("_shm_done_flags")
        indices, workers = d.get("_worker_indices"), d.get("_workers")
        return (
            self.sleep_while_waiting
            and bool(d.get("_use_buffers", False))
            and hasattr(flags, "__setitem__")
            and isinstance(indices, list)
            and isinstance(workers, list)
            and isinstance(d.get("BATCHED_PIPE_TIMEOUT"), (int, float))
        )

    # Overrides a private method of torchrl 0.14.1 (ParallelEnv._wait_for_workers, shared-
    # buffer branch); anything unexpected falls back to it (see the class docstring).
    def _wait_for_workers(self, workers_range: Iterable[int]) -> None:
        if not self._sleeping_wait_applies():
            return super()._wait_for_workers(workers_range)
        flags, indices = self._shm_done_flags, self._worker_indices
        workers = list(workers_range)
        timeout = self.BATCHED_PIPE_TIMEOUT
        start = time.monotonic()
        deadline = start + timeout
        delay = self._MIN_SLEEP
        polls = 0
        kind = self.__dict__.get("_wait_kind")
        recent = self.__dict__.setdefault("_recent_waits", {}).get(kind, 0.0)
        max_delay = self._MAX_SLEEP
        if kind is not None and recent > 0 and not all(flags[indices[i]] for i in workers):
            time.sleep(self._FIRST_SLEEP_SHARE * recent)
            # Polls spaced by a small share of the wait: few wake-ups, little overshoot.
            delay = max_delay = min(
                max(self._MIN_SLEEP, recent / self._POLLS_PER_WAIT), self._MAX_POLL_SLEEP
            )
        while not all(flags[indices[i]] for i in workers):
            polls += 1
            if polls % 64 == 0:
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"workers did not answer within {timeout} s "
                        "(raise BATCHED_PIPE_TIMEOUT if steps are that slow)"
                    )
                dead = [
                    i for i in workers if not flags[indices[i]] and not self._workers[i].is_alive()
                ]
                if dead:
                    # As TorchRL does: stop the other workers before reporting.
                    try:
                        self._shutdown_workers()
                    finally:
                        raise RuntimeError(f"Cannot proceed, worker {dead[0]} dead.")
            time.sleep(delay)
            delay = min(2 * delay, max_delay)
        if kind is not None:
            waited = time.monotonic() - start
            self._recent_waits[kind] = 0.8 * recent + 0.2 * waited if recent else waited
        for i in workers:
            flags[indices[i]] = 0
        return None

    def _wait_as(self, kind: str, workers: list[int]) -> None:
        """Wait for ``workers``, timing the wait with the other waits of ``kind``."""
        self._wait_kind = kind
        try:
            self._wait_for_workers(workers)
        finally:
            self._wait_kind = None

    # ------------------------------------------------------------ branch rollouts
    def branch_fast_paths_apply(self) -> bool:
        """Whether :meth:`branch_restore` and :meth:`branch_step` may run on this env.

        They need the worker protocol and shared buffers of torchrl 0.14.1, on CPU,
        with tensor-only entries, and workers whose step reads nothing but the action
        (and whose reset nothing but the state) from the buffers.
        """
        if not self.branch_fast_paths:
            return False
        if self.is_closed:
            self.start()
        d = self.__dict__
        shared = d.get("shared_tensordict_parent")
        channels = d.get("parent_channels")
        inputs = d.get("_env_input_keys")
        if not (
            bool(d.get("_use_buffers", False))
            and not d.get("_non_tensor_keys")
            and d.get("event") is None
            and self.device is not None
            and self.device.type == "cpu"
            and isinstance(shared, TensorDict)
            and tuple(shared.batch_size) == (self.num_workers,)
            and tuple(self.batch_size) == (self.num_workers,)
            and isinstance(channels, list)
            and len(channels) == self.num_workers
            and isinstance(inputs, list)
        ):
            return False
        actions = {unravel_key(k) for k in self.action_keys}
        return all(
            unravel_key(k) in actions or _under_state(unravel_key(k)) for k in inputs
        ) and all(k in shared.keys(True, True) for k in actions)

    def branch_restore(
        self, workers: list[int], states: TensorDictBase, keys: Sequence[NestedKey]
    ) -> TensorDict:
        """Restore ``states[i]`` in worker ``workers[i]``; return their ``keys`` entries.

        What ``reset(TensorDict(state=..., _reset=mask), set_state=True)`` does for
        these workers, without touching the others' buffers.

        Args:
            workers: the workers to restore, each once.
            states: their states, batch ``[len(workers)]``.
            keys: the reset output entries to return (e.g. observations, ``"state"``).

        Returns:
            A new tensordict of batch ``[len(workers)]``.
        """
        shared = self.shared_tensordict_parent
        index = torch.tensor(workers, dtype=torch.long)
        buffers = self.__dict__.get("_branch_state_buffers")
        if buffers is None:
            buffers = list(shared.get(STATE).items(True, True))
            self._branch_state_buffers = buffers
            # The entries a worker's reset reads from its buffer (TorchRL sends the
            # keys of the reset's input).
            self._branch_reset_keys = [(STATE, *_as_tuple(k)) for k, _ in buffers]
        # Leaf by leaf: a tensordict __setitem__ costs ~1 ms for the ~40 state leaves.
        for key, buffer in buffers:
            buffer.index_copy_(0, index, states.get(key))
        reset_keys = self._branch_reset_keys
        for i in workers:
            self.parent_channels[i].send(("reset", (reset_keys, {"set_state": True})))
        self._wait_as("restore", workers)
        return shared.select(*keys)[index]

    def branch_step(
        self, actions: TensorDictBase, workers: list[int], keys: Sequence[NestedKey]
    ) -> TensorDict:
        """Step ``workers`` with their rows of ``actions``; return the ``("next", key)`` entries.

        What ``step`` with a ``"_step"`` mask does for these workers, without copying
        anything but the actions in and ``keys`` out.

        Args:
            actions: batch ``[W]``, holding the env's action entries.
            workers: the workers to step.
            keys: the ``"next"`` entries to return.

        Returns:
            A new tensordict of batch ``[W]``; the rows of the workers not stepped are
            whatever their buffers held.
        """
        shared = self.shared_tensordict_parent
        for key in self.action_keys:
            # Rows of the workers not stepped are written too, and never read.
            shared.get(key).copy_(actions.get(key))
        for i in workers:
            self.parent_channels[i].send(("step", {}))
        self._wait_as("step", workers)
        return shared.get("next").select(*keys).clone()

    # ------------------------------------------------------------ whole branches
    def branch_workers_apply(self) -> bool:
        """Whether the workers can run whole branches.

        They need workers built from constructors (which then carry the runner of
        :class:`~torchrl_grpo.branching.worker_factory.BranchWorkerFactory`) and what
        :meth:`branch_fast_paths_apply` checks.
        """
        if not self.branch_fast_paths_apply():
            return False
        makers = self.__dict__.get("create_env_fn")
        return isinstance(makers, list) and all(isinstance(f, BranchWorkerFactory) for f in makers)

    def whole_branches_apply(self) -> bool:
        """Whether branch rollouts may run whole branches in the workers (``worker_branches``).

        They need :attr:`whole_branches` and :meth:`branch_workers_apply`; a rollout
        whose policy does not pickle for the workers still runs in the parent.
        """
        return self.whole_branches and self.branch_workers_apply()

    def branch_run_send(self, worker: int, message: tuple) -> None:
        """Queue ``message`` for ``worker``'s ``BranchRunner`` (see ``branch_runner``).

        Its answer is read, in sending order, with :meth:`branch_answer`.
        """
        try:
            self.parent_channels[worker].send(("branch_runs", ((message,), {})))
        except OSError as err:  # a broken pipe
            raise RuntimeError(f"Cannot proceed, worker {worker} dead.") from err

    def branch_ready(self, workers: Sequence[int]) -> list[int]:
        """Those of ``workers`` with an answer to read (blocks until there is one).

        The parent sleeps in the kernel until an answer arrives: no polling.

        Raises:
            RuntimeError: one of ``workers`` died, or none answered within
                ``BATCHED_PIPE_TIMEOUT``.
        """
        channels = {self.parent_channels[w]: w for w in workers}
        deadline = time.monotonic() + self.BATCHED_PIPE_TIMEOUT
        while True:
            ready = connection.wait(list(channels), timeout=1.0)
            if ready:
                return sorted(channels[c] for c in ready)
            # The parent keeps the workers' ends of the pipes open, so a dead worker
            # shows as silence: check every second.
            dead = [w for w in workers if not self._workers[w].is_alive()]
            if dead:
                raise RuntimeError(f"Cannot proceed, worker {dead[0]} dead.")
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"workers {list(workers)} did not answer within {self.BATCHED_PIPE_TIMEOUT} s"
                )

    def branch_answer(self, worker: int) -> Any:
        """The answer of ``worker`` to its oldest message not read yet (blocks until it comes).

        Raises:
            RuntimeError: the worker died or did not answer in time.
        """
        self.branch_ready([worker])
        try:
            return self.parent_channels[worker].recv()[1]
        except (EOFError, OSError) as err:  # the worker's end closed, or reset
            raise RuntimeError(f"Cannot proceed, worker {worker} dead.") from err


def _with_runner(make: Any) -> Any:
    # An env instance is sent to its worker as it is: it gets no runner.
    return make if isinstance(make, EnvBase) else BranchWorkerFactory(make)


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return key if isinstance(key, tuple) else (key,)


def _under_state(key: NestedKey) -> bool:
    return _as_tuple(key)[0] == STATE
