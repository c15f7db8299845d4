"""Worker envs for branch rollouts: builders, a parent that sleeps, clean shutdown.

Branch rollouts read every worker's state after each restore and step. Workers
built with ``HighwayEnv(..., return_state=True)`` declare ``"state"`` as an
observation, so a ``ParallelEnv`` returns it (``"state"`` after a reset,
``("next", "state")`` after a step) through its shared buffers: one shared-memory
copy instead of a pipe round trip per worker through ``penv.get_state()``.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Iterable
from typing import Any, Literal

from torchrl.envs import EnvBase, ParallelEnv, SerialEnv, TransformedEnv

from torchrl_grpo.envs import HighwayEnv

logger = logging.getLogger(__name__)

Backend = Literal["parallel", "serial", "single"]

__all__ = [
    "Backend",
    "BranchParallelEnv",
    "make_branch_env",
    "shutdown_env",
]


class BranchParallelEnv(ParallelEnv):
    """A ``ParallelEnv`` whose parent process sleeps while its workers step.

    TorchRL's ``ParallelEnv`` waits for its workers by spinning on shared-memory
    flags, which keeps one core busy in the parent. With W workers on W cores the
    workers then share W - 1 cores: on 2 cores, 2 workers ran no faster than 1 (the
    benchmark's ``W=2 spin`` row). This subclass polls the same flags with short
    sleeps (10 to 500 us, against steps of 10+ ms), leaving the cores to the workers.
    Everything else is ``ParallelEnv``.

    The override replaces a private method: it is written against torchrl 0.14.1,
    whose ``ParallelEnv._wait_for_workers(workers_range)`` waits, in shared-buffer
    mode, until the byte ``_shm_done_flags[_worker_indices[i]]`` of every worker
    ``i`` is set, then clears them. When those attributes are not there as expected
    (another TorchRL version, pipe mode with ``use_buffers=False``) or
    :attr:`sleep_while_waiting` is ``False``, TorchRL's own wait runs instead.

    Attributes:
        sleep_while_waiting: set to ``False`` to use TorchRL's spinning wait.

    Example:
        >>> import functools
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = BranchParallelEnv(1, functools.partial(HighwayEnv, "merge-v0"),
        ...                         mp_start_method="fork")
        >>> env.reset().batch_size
        torch.Size([1])
        >>> shutdown_env(env)
    """

    sleep_while_waiting: bool = True
    _MIN_SLEEP = 1e-5
    _MAX_SLEEP = 5e-4

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
        deadline = time.monotonic() + timeout
        delay = self._MIN_SLEEP
        polls = 0
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
            delay = min(2 * delay, self._MAX_SLEEP)
        for i in workers:
            flags[indices[i]] = 0
        return None


def make_branch_env(
    scenario: str,
    num_workers: int = 2,
    *,
    config: dict | None = None,
    backend: Backend = "parallel",
    snapshots: bool = True,
    mp_start_method: Literal["spawn", "fork", "forkserver"] | None = None,
    **env_kwargs: Any,
) -> EnvBase:
    """Build the env that runs branches: W :class:`~torchrl_grpo.envs.HighwayEnv` workers.

    Args:
        scenario: a highway-env scenario id, e.g. ``"highway-fast-v0"``.
        num_workers: W, the number of branches simulated at once (one per process
            with ``backend="parallel"``). ``1`` with ``"single"``.
        config: scenario config overrides, the same in every worker.
        backend: ``"parallel"`` (a :class:`BranchParallelEnv`: one process per worker),
            ``"serial"`` (a ``SerialEnv``: the same API in this process, for
            debugging) or ``"single"`` (one plain env, no batch dimension).
        snapshots: build the workers with ``return_state=True``, so that they
            return their state after every reset and step (``"state"``,
            ``("next", "state")``) and branch rollouts read states (final states,
            ``return_states=True``) from shared memory. It costs every worker step
            an encode and a copy (about 2.5 ms of a 20 ms highway-fast-v0 step).
            Without it, states are read with ``env.get_state()``, one pipe round
            trip to all workers per read (about 18 ms for 2 workers): fine for
            final states (one read per wave), slow for ``return_states=True`` (one
            read per step). Pass ``False`` for rollouts that need no states.
        mp_start_method: the ``ParallelEnv`` start method (``None``: TorchRL's
            default, ``spawn``). ``fork`` starts in well under a second instead of
            seconds, and is safe for these CPU-only workers.
        **env_kwargs: more :class:`~torchrl_grpo.envs.HighwayEnv` arguments
            (``max_vehicles``, ...). A ``return_state=True`` here returns states
            as ``snapshots=True`` does (either one turns it on).

    Returns:
        The env. The caller owns it: close it with :func:`shutdown_env` (or let a
        :class:`~torchrl_grpo.branching.GroupCollector` do it).

    Example:
        >>> env = make_branch_env("merge-v0", 2, backend="serial")
        >>> env.batch_size, "state" in env.observation_spec.keys()
        (torch.Size([2]), True)
        >>> shutdown_env(env)
    """
    if num_workers < 1:
        raise ValueError(f"num_workers must be >= 1, got {num_workers}")
    if backend not in ("parallel", "serial", "single"):
        raise ValueError(f"backend must be 'parallel', 'serial' or 'single', got {backend!r}")
    asked = bool(env_kwargs.pop("return_state", False))
    return_state = bool(snapshots) or asked
    make = functools.partial(
        HighwayEnv, scenario, config=config, return_state=return_state, **env_kwargs
    )
    if backend == "single":
        if num_workers != 1:
            raise ValueError(f"backend='single' runs one env, got num_workers={num_workers}")
        return make()
    if backend == "serial":
        return SerialEnv(num_workers, make)
    kwargs: dict[str, Any] = {}
    if mp_start_method is not None:
        kwargs["mp_start_method"] = mp_start_method
    return BranchParallelEnv(num_workers, make, **kwargs)


def shutdown_env(env: EnvBase, timeout: float = 10.0) -> None:
    """Close an env and make sure none of its worker processes survives.

    Safe to call twice, on a never-started ``ParallelEnv``, or after a worker died.

    Args:
        env: the env to close.
        timeout: seconds to wait for each worker to exit before terminating it.

    Example:
        >>> env = make_branch_env("merge-v0", 1, backend="serial")
        >>> shutdown_env(env)
        >>> shutdown_env(env)  # idempotent
    """
    try:
        if not env.is_closed:
            env.close(raise_if_closed=False)
    except Exception:
        # A dead worker must not prevent the cleanup below.
        logger.warning(
            "closing %s raised; terminating its workers", type(env).__name__, exc_info=True
        )
    # ParallelEnv keeps its processes in _workers; close() joins them, but a worker
    # stuck in a step (or after an interrupt) may still be alive.
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    # Read the instance dict: ParallelEnv.__getattr__ would start a stopped env.
    for process in base.__dict__.get("_workers") or []:
        if process.is_alive():
            process.join(timeout)
        if process.is_alive():
            logger.warning("terminating branch worker pid %s", process.pid)
            process.terminate()
            process.join(timeout)
