"""Worker envs for branch rollouts: states as observations, builders, clean shutdown.

A ``ParallelEnv`` only moves the entries its specs declare as observations through
its shared buffers. The ``"state"`` entry a :class:`~torchrl_grpo.envs.SnapshotEnv`
writes after a reset or step is part of its *state* spec, so it never leaves the
worker. :class:`SnapshotObservation` declares it as an observation under
``"snapshot"``, which lets the parent read each worker's state after every restore
and step at the cost of one shared-memory copy, instead of a pipe round trip per
worker through ``penv.get_state()``.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Iterable
from typing import Any, Literal

from tensordict import TensorDictBase
from torchrl.data import Composite
from torchrl.envs import EnvBase, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.transforms import Transform

from torchrl_grpo.branching.keys import SNAPSHOT, STATE
from torchrl_grpo.envs import HighwayEnv

logger = logging.getLogger(__name__)

Backend = Literal["parallel", "serial", "single"]

# Scenarios that spawn vehicles size their state padding from the first reset, which
# depends on the seed, so workers built with different seeds would have different
# state layouts (a known envs issue). A fixed padding keeps every worker's layout equal.
DEFAULT_PADDING: dict[str, dict[str, int]] = {"intersection-v0": {"max_vehicles": 32}}

__all__ = [
    "DEFAULT_PADDING",
    "Backend",
    "BranchParallelEnv",
    "SnapshotObservation",
    "make_branch_env",
    "shutdown_env",
]


class SnapshotObservation(Transform):
    """Publishes the env's complete state as an observation after every reset and step.

    Put it inside each worker of a batched env (see :func:`make_branch_env`) so that
    ``"snapshot"`` (and ``("next", "snapshot")``) reach the parent process through
    the shared buffers. The base env must be a
    :class:`~torchrl_grpo.envs.SnapshotEnv` (it provides ``get_state()``).

    Example:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_grpo.envs import HighwayEnv, states_equal
        >>> env = TransformedEnv(HighwayEnv("merge-v0", seed=0), SnapshotObservation())
        >>> td = env.reset()
        >>> states_equal(td["snapshot"], env.base_env.get_state())
        True
    """

    def __init__(self) -> None:
        super().__init__(in_keys=[], out_keys=[SNAPSHOT])

    def _base_state(self) -> TensorDictBase:
        return self.parent.base_env.get_state()

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        state = tensordict_reset.get(STATE, None)
        tensordict_reset.set(SNAPSHOT, self._base_state() if state is None else state)
        return tensordict_reset

    def _step(
        self, tensordict: TensorDictBase, next_tensordict: TensorDictBase
    ) -> TensorDictBase:
        # An env built with return_state=True already encoded the state: reuse it.
        state = next_tensordict.pop(STATE, None)
        next_tensordict.set(SNAPSHOT, self._base_state() if state is None else state)
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        """Add the base env's state spec under ``"snapshot"``."""
        base = self.parent.base_env
        observation_spec[SNAPSHOT] = base.state_spec[STATE].clone()
        return observation_spec

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Not usable outside an env: the state lives in the simulator."""
        raise RuntimeError("SnapshotObservation only works inside a TransformedEnv")


class BranchParallelEnv(ParallelEnv):
    """A ``ParallelEnv`` whose parent process sleeps while its workers step.

    TorchRL 0.14's ``ParallelEnv`` waits for its workers by spinning on shared-memory
    flags, which keeps one core busy in the parent. With W workers on W cores the
    workers then share W - 1 cores: on 2 cores, 2 workers ran no faster than 1. This
    subclass polls the same flags with short sleeps (10 to 500 us, against steps of
    10+ ms), leaving the cores to the workers. Everything else is ``ParallelEnv``.

    Example:
        >>> import functools
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = BranchParallelEnv(1, functools.partial(HighwayEnv, "merge-v0"),
        ...                         mp_start_method="fork")
        >>> env.reset().batch_size
        torch.Size([1])
        >>> shutdown_env(env)
    """

    _MIN_SLEEP = 1e-5
    _MAX_SLEEP = 5e-4

    def _wait_for_workers(self, workers_range: Iterable[int]) -> None:
        flags = self.__dict__.get("_shm_done_flags")
        indices = self.__dict__.get("_worker_indices")
        if not self._use_buffers or flags is None or indices is None:
            # Another TorchRL version or the pipe mode: keep TorchRL's own wait.
            return super()._wait_for_workers(workers_range)
        workers = list(workers_range)
        deadline = time.monotonic() + self.BATCHED_PIPE_TIMEOUT
        delay = self._MIN_SLEEP
        polls = 0
        while not all(flags[indices[i]] for i in workers):
            polls += 1
            if polls % 64 == 0:
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"workers did not answer within {self.BATCHED_PIPE_TIMEOUT} s "
                        "(raise BATCHED_PIPE_TIMEOUT if steps are that slow)"
                    )
                for i in workers:
                    if not flags[indices[i]] and not self._workers[i].is_alive():
                        raise RuntimeError(f"Cannot proceed, worker {i} dead.")
            time.sleep(delay)
            delay = min(2 * delay, self._MAX_SLEEP)
        for i in workers:
            flags[indices[i]] = 0
        return None


def _make_worker(
    scenario: str, config: dict | None, snapshots: bool, env_kwargs: dict[str, Any]
) -> EnvBase:
    env = HighwayEnv(scenario, config=config, **{**DEFAULT_PADDING.get(scenario, {}), **env_kwargs})
    return TransformedEnv(env, SnapshotObservation()) if snapshots else env


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
        snapshots: add :class:`SnapshotObservation` to every worker, so branch
            rollouts read states (final states, ``return_states=True``) from
            shared memory. It costs every worker step an encode and a copy (about
            2.5 ms of a 20 ms highway-fast-v0 step). Without it, states are read
            with ``env.get_state()``, one pipe round trip to all workers per read
            (about 18 ms for 2 workers): fine for final states (one read per wave),
            slow for ``return_states=True`` (one read per step). Pass ``False``
            for rollouts that need no states.
        mp_start_method: the ``ParallelEnv`` start method (``None``: TorchRL's
            default, ``spawn``). ``fork`` starts in well under a second instead of
            seconds, and is safe for these CPU-only workers.
        **env_kwargs: more :class:`~torchrl_grpo.envs.HighwayEnv` arguments
            (``max_vehicles``, ``return_state``, ...). intersection-v0 defaults to
            ``max_vehicles=32`` (see :data:`DEFAULT_PADDING`): build the envs that
            produce its root states with the same padding.

    Returns:
        The env. The caller owns it: close it with :func:`shutdown_env` (or let a
        :class:`~torchrl_grpo.branching.GroupCollector` do it).

    Example:
        >>> env = make_branch_env("merge-v0", 2, backend="serial")
        >>> env.batch_size
        torch.Size([2])
        >>> shutdown_env(env)
    """
    if num_workers < 1:
        raise ValueError(f"num_workers must be >= 1, got {num_workers}")
    if backend not in ("parallel", "serial", "single"):
        raise ValueError(f"backend must be 'parallel', 'serial' or 'single', got {backend!r}")
    if backend == "single":
        if num_workers != 1:
            raise ValueError(f"backend='single' runs one env, got num_workers={num_workers}")
        return _make_worker(scenario, config, snapshots, env_kwargs)
    make = functools.partial(_make_worker, scenario, config, snapshots, env_kwargs)
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

