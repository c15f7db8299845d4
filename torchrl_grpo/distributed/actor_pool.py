"""The Ray actors of a :class:`~torchrl_grpo.distributed.RayGroupCollector`.

:func:`split_groups` shares a batch's groups among the actors; an :class:`ActorPool`
starts the actors, asks them for their share of every batch, and replaces an actor that
dies by a new one restored from the dead one's last snapshot.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any

from torchrl.envs import EnvBase

from torchrl_grpo.branching.roots import RootSource
from torchrl_grpo.distributed.worker import (
    GroupResult,
    GroupWorker,
    WorkerSnapshot,
    actor_seed,
    shared_root_policy,
)

logger = logging.getLogger(__name__)

__all__ = ["ActorPool", "split_groups"]


def split_groups(groups_per_batch: int, num_actors: int) -> list[int]:
    """How many groups each actor collects per batch: as even as possible, first ones first.

    Example:
        >>> split_groups(8, 3)
        [3, 3, 2]
    """
    if num_actors < 1:
        raise ValueError(f"num_actors must be >= 1, got {num_actors}")
    if groups_per_batch < num_actors:
        raise ValueError(
            f"groups_per_batch ({groups_per_batch}) must be >= num_actors ({num_actors}): "
            "every actor collects at least one group per batch"
        )
    base, extra = divmod(groups_per_batch, num_actors)
    return [base + (a < extra) for a in range(num_actors)]


class ActorPool:
    """One :class:`~torchrl_grpo.distributed.worker.GroupWorker` Ray actor per index, kept alive.

    Actor ``a`` collects ``groups_per_actor[a]`` groups per batch with the seed
    ``actor_seed(seed, a)``. The pool keeps every actor's last snapshot: a new actor
    (started lazily, or replacing a dead one) is restored from it.

    Args:
        ray: the ``ray`` module (see :func:`~torchrl_grpo.distributed.ray_setup.require_ray`).
        env_factory: a picklable callable building the branch env in an actor.
        policy: the policy; one copy goes to Ray's object store for all actors.
        roots: each actor's ``roots`` argument (a ``RootSource`` is copied per actor).
        collector_kwargs: the other :class:`~torchrl_grpo.branching.GroupCollector`
            arguments of every actor.
        groups_per_actor: groups per batch of each actor (:func:`split_groups`).
        seed: the collection's seed.
        actor_options: ``ray.remote`` options of the actors (``num_cpus`` included).
        num_threads: torch threads inside an actor.
        max_restarts: replacements allowed per actor and batch before giving up.
        wait_timeout: seconds to wait for a batch before failing with a sizing hint.

    Example:
        >>> import functools
        >>> from torchrl_grpo.branching import make_branch_env
        >>> from torchrl_grpo.distributed import init_ray
        >>> from torchrl_grpo.distributed.ray_setup import require_ray
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> started = init_ray(num_cpus=2)  # doctest: +SKIP
        >>> pool = ActorPool(require_ray(), functools.partial(make_branch_env, "merge-v0", 1,
        ...                  backend="single"), RandomPolicy(seed=0), ["reset", "reset"],
        ...                  dict(group_size=2, horizon=2), split_groups(3, 2), seed=0,
        ...                  actor_options={"num_cpus": 0.5})  # doctest: +SKIP
        >>> results = pool.gather(None, first_ids=[0, 2])  # doctest: +SKIP
        >>> [r.data.batch_size for r in results]  # doctest: +SKIP
        [torch.Size([2, 2, 2]), torch.Size([1, 2, 2])]
        >>> pool.close(timeout=10.0)  # doctest: +SKIP
    """

    def __init__(
        self,
        ray: ModuleType,
        env_factory: Callable[[], EnvBase],
        policy: Any,
        roots: Sequence[Any],
        collector_kwargs: dict[str, Any],
        groups_per_actor: list[int],
        seed: int,
        actor_options: dict[str, Any],
        num_threads: int | None = 1,
        max_restarts: int = 3,
        wait_timeout: float | None = 600.0,
    ) -> None:
        self.ray = ray
        self.env_factory = env_factory
        self.policy = policy
        self.roots = list(roots)
        # Computed before the roots are copied: the copy no longer shares the policy.
        self.root_policies = [shared_root_policy(policy, r) for r in self.roots]
        self.collector_kwargs = collector_kwargs
        self.groups_per_actor = groups_per_actor
        self.num_actors = len(groups_per_actor)
        self.seed = int(seed)
        self.actor_options = actor_options
        self.num_threads = num_threads
        self.max_restarts = max_restarts
        self.wait_timeout = wait_timeout
        self.actors: list[Any] = []
        self.snapshots: list[WorkerSnapshot | None] = [None] * self.num_actors
        self.trunk_frames = [0] * self.num_actors
        self.restarts = 0
        self._policy_ref = None

    def check_resources(self) -> None:
        """Fail early, with a sizing hint, when the cluster cannot hold the actors."""
        need = self.num_actors * self.actor_options["num_cpus"]
        have = float(self.ray.cluster_resources().get("CPU", 0.0))
        if need > have:
            raise ValueError(
                f"{self.num_actors} actors x {self.actor_options['num_cpus']} CPUs need {need} "
                f"Ray CPUs but the cluster has {have}: lower num_cpus_per_actor or num_actors, "
                "or add nodes"
            )

    def _new_actor(self, index: int) -> Any:
        ray = self.ray
        if self._policy_ref is None:
            self._policy_ref = ray.put(self.policy)
        remote_cls = ray.remote(GroupWorker).options(**self.actor_options)
        roots = self.roots[index]
        kwargs = dict(self.collector_kwargs, groups_per_batch=self.groups_per_actor[index])
        # A RootSource object is copied per actor, so actors never share one.
        kwargs["roots"] = copy.deepcopy(roots) if isinstance(roots, RootSource) else roots
        seed = actor_seed(self.seed, index)
        return remote_cls.remote(
            self.env_factory,
            self._policy_ref,
            kwargs,
            seed,
            self.num_threads,
            self.root_policies[index],
        )

    def start(self) -> None:
        """Start the actors, restored from their snapshots, unless they run already."""
        if self.actors:
            return
        self.actors = [self._new_actor(a) for a in range(self.num_actors)]
        self._restore(self.snapshots)

    def state_dict(self) -> dict[str, Any]:
        """The seed, every actor's trunk frames and snapshot, the restarts so far."""
        return {
            "seed": self.seed,
            "trunk_frames": list(self.trunk_frames),
            "snapshots": list(self.snapshots),
            "restarts": self.restarts,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; running actors continue from its snapshots."""
        self.seed = int(state_dict["seed"])
        self.trunk_frames = [int(x) for x in state_dict["trunk_frames"]]
        self.restarts = int(state_dict.get("restarts", 0))
        self._restore(state_dict["snapshots"])

    def _restore(self, snapshots: Sequence[WorkerSnapshot | None]) -> None:
        self.snapshots = list(snapshots)
        if self.actors:
            restores = [
                actor.restore.remote(snap)
                for actor, snap in zip(self.actors, self.snapshots, strict=True)
                if snap is not None
            ]
            self.ray.get(restores)

    def set_seed(self, seed: int) -> None:
        """Reseed the collection; running actors are reseeded as fresh ones would be."""
        self.seed = int(seed)
        if self.actors:
            refs = [a.set_seed.remote(actor_seed(self.seed, i)) for i, a in enumerate(self.actors)]
            self.snapshots = list(self.ray.get(refs))

    def _replace(self, index: int, err: BaseException) -> None:
        """Start a new actor ``index`` where the dead one's last batch left off."""
        ray = self.ray
        self.restarts += 1
        logger.warning(
            "Ray actor %d died (%s): replacing it and redoing its batch",
            index,
            type(err).__name__,
        )
        try:
            ray.kill(self.actors[index], no_restart=True)
        except Exception:  # noqa: BLE001 - already gone is the expected case
            pass
        actor = self._new_actor(index)
        snapshot = self.snapshots[index]
        if snapshot is not None:
            ray.get(actor.restore.remote(snapshot))
        self.actors[index] = actor

    def _fault_types(self) -> tuple[type[BaseException], ...]:
        exc = self.ray.exceptions
        types = [exc.RayActorError]
        for name in ("ActorUnavailableError", "WorkerCrashedError", "ObjectLostError"):
            if hasattr(exc, name):
                types.append(getattr(exc, name))
        return tuple(types)

    def gather(self, weights: Any, first_ids: list[int], batch: int = 0) -> list[GroupResult]:
        """Every actor's share of one batch, its group ids starting at ``first_ids[a]``.

        An actor that dies is replaced and asked again, with the same ``weights``. The
        results are not kept: :meth:`keep` takes them once the batch is complete.

        Args:
            weights: the policy's weights (an object-store reference), or ``None``.
            first_ids: each actor's first group id.
            batch: the batch's index, for error messages.
        """
        ray = self.ray
        self.start()
        faults = self._fault_types()
        pending = {
            actor.collect.remote(weights, first_ids[a]): a for a, actor in enumerate(self.actors)
        }
        results: list[GroupResult | None] = [None] * self.num_actors
        tries = [0] * self.num_actors
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=self.wait_timeout)
            if not ready:
                raise TimeoutError(
                    f"no actor answered within {self.wait_timeout} s: are the actors "
                    f"schedulable ({self.actor_options}) on {ray.available_resources()}?"
                )
            ref = ready[0]
            a = pending.pop(ref)
            try:
                results[a] = ray.get(ref)
            except faults as err:
                tries[a] += 1
                if tries[a] > self.max_restarts:
                    raise RuntimeError(
                        f"Ray actor {a} died {tries[a]} times on batch {batch}"
                    ) from err
                self._replace(a, err)
                pending[self.actors[a].collect.remote(weights, first_ids[a])] = a
        return results  # type: ignore[return-value]

    def keep(self, results: list[GroupResult]) -> None:
        """Take the snapshots and trunk frames of a complete batch's results."""
        for a, result in enumerate(results):
            self.snapshots[a] = result.snapshot
            self.trunk_frames[a] = int(result.trunk_frames)

    def close(self, timeout: float) -> None:
        """Close every actor's env workers and end the actors (dead ones are skipped)."""
        ray = self.ray
        if not self.actors:
            return
        refs = [a.close.remote() for a in self.actors]
        # Actors that are already dead cannot close anything: ignore them.
        ray.wait(refs, num_returns=len(refs), timeout=timeout)
        for actor in self.actors:
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # noqa: BLE001, S110
                pass
        self.actors = []
