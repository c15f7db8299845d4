"""Building the env that runs branches, and closing it without leaving a worker behind.

:func:`make_branch_env` builds W snapshot-env workers (highway-env scenarios, any env id
with a registered state codec, or a factory) as a
:class:`~torchrl_grpo.branching.BranchParallelEnv`, a
:class:`~torchrl_grpo.envs.SnapshotSerialEnv` or one plain env; :func:`shutdown_env`
closes any of them.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from typing import Any, Literal

from torchrl.envs import EnvBase, TransformedEnv

from torchrl_grpo.branching.workers import BranchParallelEnv
from torchrl_grpo.envs.core.codec_registry import codec_for
from torchrl_grpo.envs.core.snapshot_batched import SnapshotSerialEnv
from torchrl_grpo.envs.core.snapshot_env import SnapshotEnv
from torchrl_grpo.envs.highway.highway_codec import HIGHWAY_SCENARIOS
from torchrl_grpo.envs.highway.wrapper import HighwayEnv

logger = logging.getLogger(__name__)

Backend = Literal["parallel", "serial", "single"]

__all__ = ["Backend", "make_branch_env", "shutdown_env"]


def make_branch_env(
    env: str | Callable[..., EnvBase],
    num_workers: int = 2,
    *,
    config: dict | None = None,
    backend: Backend = "parallel",
    snapshots: bool = True,
    mp_start_method: Literal["spawn", "fork", "forkserver"] | None = None,
    **env_kwargs: Any,
) -> EnvBase:
    """Build the env that runs branches: W snapshot-env workers.

    Args:
        env: what each worker runs: a highway-env scenario id (``"highway-fast-v0"``:
            :class:`~torchrl_grpo.envs.HighwayEnv` workers), another env id with a
            registered state codec (``"CartPole-v1"``: :class:`~torchrl_grpo.envs.SnapshotEnv`
            workers, see :func:`~torchrl_grpo.envs.register_codec`), or a factory that
            builds one snapshot env and accepts ``return_state=`` (e.g.
            ``functools.partial(SnapshotEnv, "CartPole-v1")``).
        num_workers: W, the number of branches simulated at once (one per process
            with ``backend="parallel"``). ``1`` with ``"single"``.
        config: highway-env config overrides, the same in every worker (highway-env
            scenarios only).
        backend: ``"parallel"`` (a :class:`BranchParallelEnv`: one process per worker),
            ``"serial"`` (a :class:`~torchrl_grpo.envs.SnapshotSerialEnv`: the same
            API in this process, for debugging) or ``"single"`` (one plain env, no batch dimension).
        snapshots: build the workers with ``return_state=True``, so that they
            return their state after every reset and step (``"state"``,
            ``("next", "state")``) and branch rollouts read states (final states,
            ``return_states=True``) from shared memory. It costs every worker step
            an encode (~0.2 ms) and TorchRL's copies of the state's ~40 leaves in
            the worker (together ~1.5 ms of a ~20 ms highway-fast-v0 step), even
            in rollouts that keep no states: the workers' buffers follow their specs.
            Without it, states are read with ``env.get_state()``, one pipe round
            trip to all workers per read (about 18 ms for 2 workers): fine for
            final states (one read per wave), slow for ``return_states=True`` (one
            read per step). Pass ``False`` for rollouts that need no states.
        mp_start_method: the ``ParallelEnv`` start method (``None``: TorchRL's
            default, ``spawn``). ``fork`` starts in well under a second instead of
            seconds, and is safe for these CPU-only workers.
        **env_kwargs: more arguments of the worker env (``max_vehicles``, ...). A
            ``return_state=True`` here returns states as ``snapshots=True`` does
            (either one turns it on).

    Returns:
        The env. The caller owns it: close it with :func:`shutdown_env` (or let a
        :class:`~torchrl_grpo.branching.GroupCollector` do it).

    Example:
        >>> env = make_branch_env("merge-v0", 2, backend="serial")
        >>> env.batch_size, "state" in env.observation_spec.keys()
        (torch.Size([2]), True)
        >>> shutdown_env(env)
        >>> cartpole = make_branch_env("CartPole-v1", 2, backend="serial")  # any codec's env
        >>> cartpole.batch_size
        torch.Size([2])
        >>> shutdown_env(cartpole)
    """
    if num_workers < 1:
        raise ValueError(f"num_workers must be >= 1, got {num_workers}")
    if backend not in ("parallel", "serial", "single"):
        raise ValueError(f"backend must be 'parallel', 'serial' or 'single', got {backend!r}")
    asked = bool(env_kwargs.pop("return_state", False))
    return_state = bool(snapshots) or asked
    make = _worker_factory(env, config, return_state, env_kwargs)
    if backend == "single":
        if num_workers != 1:
            raise ValueError(f"backend='single' runs one env, got num_workers={num_workers}")
        return make()
    if backend == "serial":
        return SnapshotSerialEnv(num_workers, make)
    kwargs: dict[str, Any] = {}
    if mp_start_method is not None:
        kwargs["mp_start_method"] = mp_start_method
    return BranchParallelEnv(num_workers, make, **kwargs)


def _worker_factory(
    env: str | Callable[..., EnvBase], config: dict | None, return_state: bool, kwargs: dict
) -> Callable[[], EnvBase]:
    """A picklable callable that builds one worker env."""
    if callable(env) and not isinstance(env, str):
        if config is not None:
            raise ValueError("config= applies to highway-env scenario ids; pass it to the factory")
        return functools.partial(env, return_state=return_state, **kwargs)
    if not isinstance(env, str):
        raise TypeError(f"env must be an env id or a factory, got {type(env).__name__}")
    if env in HIGHWAY_SCENARIOS:
        return functools.partial(
            HighwayEnv, env, config=config, return_state=return_state, **kwargs
        )
    codec_for(env)  # raises a KeyError naming the registered ids
    if config is not None:
        raise ValueError(f"config= applies to highway-env scenario ids, not to {env!r}")
    return functools.partial(SnapshotEnv, env, return_state=return_state, **kwargs)


def shutdown_env(env: EnvBase, timeout: float = 10.0) -> None:
    """Close an env and make sure none of its worker processes survives.

    Safe to call twice, on a never-started ``ParallelEnv``, or after a worker died.

    Args:
        env: the env to close.
        timeout: seconds to wait for each worker to exit before terminating it, and
            again before killing it.

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
        if getattr(process, "_closed", False):
            # TorchRL closes the others' process objects when it finds a dead worker
            # (it has terminated and reaped them): is_alive() would raise.
            continue
        if process.is_alive():
            process.join(timeout)
        if process.is_alive():
            logger.warning("terminating branch worker pid %s", process.pid)
            process.terminate()
            process.join(timeout)
        if process.is_alive():
            # One outlived SIGTERM (a forked worker, on a loaded machine, in the test
            # suite): SIGKILL cannot be caught or blocked.
            logger.warning("killing branch worker pid %s (it outlived SIGTERM)", process.pid)
            process.kill()
            process.join(timeout)
