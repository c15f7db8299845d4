"""RayGroupCollector: branch groups collected by Ray actors, gathered by the learner."""

from __future__ import annotations

import copy
import logging
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.collectors import BaseCollector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching import MASK, RootKind, RootSource
from torchrl_grpo.branching.continuation import Selection
from torchrl_grpo.branching.rollout import RngMode, check_group_args
from torchrl_grpo.distributed._ray import init_ray, require_ray
from torchrl_grpo.distributed.worker import GroupResult, GroupWorker, WorkerSnapshot, actor_seed

logger = logging.getLogger(__name__)

__all__ = ["RayGroupCollector", "split_groups"]


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


class RayGroupCollector(BaseCollector):
    """A :class:`~torchrl_grpo.branching.GroupCollector` spread over Ray actors.

    Each of the ``num_actors`` actors owns a ``GroupCollector`` with its own env workers
    (built in the actor by ``env_factory``). Every batch, the learner puts the policy's
    current weights in Ray's object store once, asks every actor for its share of the
    ``groups_per_batch`` groups (:func:`split_groups`), waits for all of them and yields
    their concatenation, ``[R, G, T]`` like the local collector (actor 0's groups first).
    Collection is synchronous: every batch is sampled by the weights of the previous
    update, as with the local collector.

    **Group ids** are assigned by the learner: batch k, actor a starts at
    ``k * R + sum(R_b for b < a)``, so ids are unique and a batch's ids are contiguous.

    **Seeds**: actor a uses ``actor_seed(seed, a)`` for
    its collector and for its torch generator (from which the policy samples); actor 0
    uses ``seed``. With one actor and a fixed policy the batches are bitwise those of
    ``GroupCollector(env, policy, seed=seed, ...)`` followed by ``torch.manual_seed(seed)``;
    with several, actor a's share is that of such a local collector with seed
    ``actor_seed(seed, a)``, ``R_a`` groups per batch and the group ids above.

    **Faults**: after every batch each actor returns a snapshot of its state (counters,
    root source, torch generator) with its groups. When an actor dies (its process is
    killed, its node is lost), the learner starts a new actor, restores the dead one's
    last snapshot and asks for the same batch again with the same weights: the redone
    batch is bitwise the one the dead actor would have returned, nothing it had done is
    counted, and no group is lost or duplicated. An error raised by the collection
    itself is not a fault: it stops the collection.

    Frames count the valid branch steps of the yielded batches (``mask.sum()``);
    :attr:`trunk_frames` sums the actors' trunk steps.

    Args:
        env_factory: a picklable callable that builds the branch env in an actor, e.g.
            ``functools.partial(make_branch_env, "merge-v0", 2)`` (an env instance
            cannot be shipped: its worker processes belong to this process).
        policy: the learner's policy; a copy goes to every actor, and its weights are
            sent before every batch.
        num_actors: how many Ray actors collect.
        group_size: G >= 2.
        horizon: T >= 1.
        groups_per_batch: R, groups per batch over all actors (>= ``num_actors``).
        total_frames: stop after this many branch steps (``-1``: never).
        roots: ``"reset"``, ``"trunk"``, ``"continue"``, a ``RootSource`` (copied to
            every actor: each copy runs on its own) or one ``RootSource`` per actor.
        decision_interval: K for ``roots="trunk"``.
        select: branch selection of ``roots="continue"``.
        temperature: softmax temperature of ``select="sampled"``.
        rng: ``"shared"`` or ``"per_branch"`` simulator randomness.
        seed: the collection's seed (``None``: drawn from torch's global generator).
        return_states: add the states to every step.
        set_truncated: see :func:`~torchrl_grpo.branching.branch_rollout`.
        exploration_type: how the policy acts.
        num_cpus_per_actor: Ray logical CPUs reserved per actor (size it to the env
            workers it runs: about ``num_workers`` for a parallel env).
        memory_per_actor: bytes of memory Ray reserves per actor (``None``: no
            reservation).
        actor_options: more ``ray.remote`` options of the actors.
        num_threads: torch threads inside an actor.
        max_restarts: replacements allowed per actor and batch before giving up.
        wait_timeout: seconds to wait for a batch before failing with a sizing hint
            (actors that do not fit on the cluster wait forever otherwise).
        ray_init: ``ray.init`` arguments used when Ray is not running yet (see
            :func:`~torchrl_grpo.distributed.init_ray`); the collector then shuts Ray
            down with itself.

    Example:
        >>> import functools
        >>> from torchrl_grpo.branching import make_branch_env
        >>> from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor
        >>> policy = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
        >>> env_factory = functools.partial(make_branch_env, "merge-v0", 1, backend="single")
        >>> with RayGroupCollector(env_factory, policy, num_actors=2, group_size=2, horizon=2,
        ...                        groups_per_batch=2, total_frames=16, seed=0,
        ...                        num_cpus_per_actor=0.5,
        ...                        ray_init={"num_cpus": 2}) as collector:  # doctest: +SKIP
        ...     for batch in collector:
        ...         print(batch.batch_size, batch["group_id"][:, 0, 0].tolist())
        torch.Size([2, 2, 2]) [0, 1]
        torch.Size([2, 2, 2]) [2, 3]
    """

    def __init__(
        self,
        env_factory: Callable[[], EnvBase],
        policy: TensorDictModuleBase | nn.Module | Callable,
        *,
        num_actors: int = 1,
        group_size: int,
        horizon: int,
        groups_per_batch: int,
        total_frames: int = -1,
        roots: RootKind | RootSource | Sequence[RootSource] = "reset",
        decision_interval: int | None = None,
        select: Selection = "best",
        temperature: float = 1.0,
        rng: RngMode = "shared",
        seed: int | None = None,
        return_states: bool = False,
        set_truncated: bool = True,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        num_cpus_per_actor: float = 1.0,
        memory_per_actor: int | None = None,
        actor_options: dict[str, Any] | None = None,
        num_threads: int | None = 1,
        max_restarts: int = 3,
        wait_timeout: float | None = 600.0,
        ray_init: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self._actors: list[Any] = []
        self._closed = True  # until Ray is up: nothing to shut down
        self._owns_ray = False
        self._ray = require_ray()
        if isinstance(env_factory, EnvBase) or not callable(env_factory):
            raise TypeError(
                "env_factory must be a picklable callable building the env in the actor "
                "(e.g. functools.partial(make_branch_env, scenario, W)), not an env"
            )
        check_group_args(group_size, horizon, rng)
        if total_frames == 0 or total_frames < -1:
            raise ValueError(f"total_frames must be > 0 or -1, got {total_frames}")
        if max_restarts < 0:
            raise ValueError(f"max_restarts must be >= 0, got {max_restarts}")
        self.groups_per_actor = split_groups(groups_per_batch, num_actors)
        if isinstance(roots, Sequence) and not isinstance(roots, str):
            if len(roots) != num_actors:
                raise ValueError(f"got {len(roots)} root sources for {num_actors} actors")
            self._roots = list(roots)
        else:
            self._roots = [roots] * num_actors
        self.env_factory = env_factory
        self.policy = policy
        self.num_actors = num_actors
        self.group_size = group_size
        self.horizon = horizon
        self.groups_per_batch = groups_per_batch
        self.total_frames = total_frames
        self.frames_per_batch = groups_per_batch * group_size * horizon
        self.requested_frames_per_batch = self.frames_per_batch
        self._collector_kwargs = dict(
            group_size=group_size,
            horizon=horizon,
            decision_interval=decision_interval,
            select=select,
            temperature=temperature,
            rng=rng,
            return_states=return_states,
            set_truncated=set_truncated,
            exploration_type=exploration_type,
        )
        options = {"num_cpus": float(num_cpus_per_actor), **(actor_options or {})}
        if memory_per_actor is not None:
            options["memory"] = int(memory_per_actor)
        self.actor_options = options
        self.num_threads = num_threads
        self.max_restarts = max_restarts
        self.wait_timeout = wait_timeout
        self.restarts = 0
        self._frames = 0
        self._batches = 0
        self._next_group_id = 0
        self._trunk_frames = [0] * num_actors
        self._snapshots: list[WorkerSnapshot | None] = [None] * num_actors
        # Seeds drawn here (not in the actors) keep an unseeded run reproducible
        # under torch.manual_seed, like the local collector.
        self._seed = int(torch.randint(0, 2**31 - 1, ())) if seed is None else int(seed)
        self._policy_ref = None
        self._owns_ray = init_ray(**(ray_init or {}))
        self._closed = False
        try:
            self._check_resources()
        except Exception:
            self.shutdown()
            raise

    # ------------------------------------------------------------------ actors
    def _check_resources(self) -> None:
        need = self.num_actors * self.actor_options["num_cpus"]
        have = float(self._ray.cluster_resources().get("CPU", 0.0))
        if need > have:
            raise ValueError(
                f"{self.num_actors} actors x {self.actor_options['num_cpus']} CPUs need {need} "
                f"Ray CPUs but the cluster has {have}: lower num_cpus_per_actor or num_actors, "
                "or add nodes"
            )

    def _seed_of(self, actor: int) -> int:
        return actor_seed(self._seed, actor)

    def _new_actor(self, index: int) -> Any:
        ray = self._ray
        if self._policy_ref is None:
            self._policy_ref = ray.put(self.policy)
        remote_cls = ray.remote(GroupWorker).options(**self.actor_options)
        roots = self._roots[index]
        kwargs = dict(self._collector_kwargs, groups_per_batch=self.groups_per_actor[index])
        # A RootSource object is copied per actor, so actors never share one.
        kwargs["roots"] = copy.deepcopy(roots) if isinstance(roots, RootSource) else roots
        return remote_cls.remote(
            self.env_factory, self._policy_ref, kwargs, self._seed_of(index), self.num_threads
        )

    def _ensure_actors(self) -> None:
        if self._closed:
            raise RuntimeError("this RayGroupCollector has been shut down")
        if self._actors:
            return
        self._actors = [self._new_actor(a) for a in range(self.num_actors)]
        restores = [
            actor.restore.remote(snap)
            for actor, snap in zip(self._actors, self._snapshots, strict=True)
            if snap is not None
        ]
        self._ray.get(restores)

    def _replace(self, index: int, err: BaseException) -> None:
        """Start a new actor ``index`` where the dead one's last batch left off."""
        ray = self._ray
        self.restarts += 1
        logger.warning(
            "Ray actor %d died (%s): replacing it and redoing its batch",
            index,
            type(err).__name__,
        )
        try:
            ray.kill(self._actors[index], no_restart=True)
        except Exception:  # noqa: BLE001 - already gone is the expected case
            pass
        actor = self._new_actor(index)
        snapshot = self._snapshots[index]
        if snapshot is not None:
            ray.get(actor.restore.remote(snapshot))
        self._actors[index] = actor

    def _fault_types(self) -> tuple[type[BaseException], ...]:
        exc = self._ray.exceptions
        types = [exc.RayActorError]
        for name in ("ActorUnavailableError", "WorkerCrashedError", "ObjectLostError"):
            if hasattr(exc, name):
                types.append(getattr(exc, name))
        return tuple(types)

    def _gather(self, weights: Any, first_ids: list[int]) -> list[GroupResult]:
        ray = self._ray
        faults = self._fault_types()
        pending = {
            actor.collect.remote(weights, first_ids[a]): a for a, actor in enumerate(self._actors)
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
                        f"Ray actor {a} died {tries[a]} times on batch {self._batches}"
                    ) from err
                self._replace(a, err)
                pending[self._actors[a].collect.remote(weights, first_ids[a])] = a
        return results  # type: ignore[return-value]

    # ------------------------------------------------------------------ iteration
    @property
    def frames(self) -> int:
        """Branch steps collected so far (valid steps of the yielded batches)."""
        return self._frames

    @property
    def trunk_frames(self) -> int:
        """Trunk steps simulated by all actors (``roots="trunk"``)."""
        return int(sum(self._trunk_frames))

    @property
    def actors(self) -> list[Any]:
        """The live Ray actor handles, one per actor index (tests kill them)."""
        return list(self._actors)

    def __iter__(self) -> Iterator[TensorDictBase]:
        """Iterate over batches; any error or interrupt shuts the actors down."""
        try:
            yield from self.iterator()
        except GeneratorExit:
            raise
        except BaseException:
            self.shutdown()
            raise

    def iterator(self) -> Iterator[TensorDictBase]:
        """Yield ``[R, G, T]`` batches until ``total_frames`` (or the roots run out)."""
        while self.total_frames < 0 or self._frames < self.total_frames:
            if self._pre_collect_hook is not None:
                self._pre_collect_hook()
            batch = self._collect()
            if batch is None:
                break
            if self._post_collect_hook is not None:
                self._post_collect_hook(batch)
            yield batch
        self.shutdown()

    def _weights(self) -> Any:
        if not isinstance(self.policy, nn.Module):
            return None
        # One copy in the object store per batch, read by every actor.
        return self._ray.put(TensorDict.from_module(self.policy).data.clone())

    def _collect(self) -> TensorDict | None:
        self._ensure_actors()
        first_ids, offset = [], self._next_group_id
        for n in self.groups_per_actor:
            first_ids.append(offset)
            offset += n
        results = self._gather(self._weights(), first_ids)
        parts = [r.data for r in results if r.data is not None and r.data.shape[0] > 0]
        if not parts:
            return None
        data = torch.cat(parts) if len(parts) > 1 else parts[0]
        for a, result in enumerate(results):
            self._snapshots[a] = result.snapshot
            self._trunk_frames[a] = int(result.trunk_frames)
        self._next_group_id = offset
        self._frames += int(data.get(MASK).sum())
        self._batches += 1
        return data

    # ------------------------------------------------------------------ TorchRL API
    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Reseed the collection; running actors are reseeded as fresh ones would be.

        Returns:
            ``seed`` (each actor derives its own, see :func:`actor_seed`).
        """
        self._seed = int(seed)
        if self._actors:
            refs = [a.set_seed.remote(self._seed_of(i)) for i, a in enumerate(self._actors)]
            self._snapshots = list(self._ray.get(refs))
        return self._seed

    def update_policy_weights_(
        self,
        policy_or_weights: TensorDictBase | nn.Module | dict | None = None,
        **kwargs: Any,
    ) -> None:
        """Load new weights into the learner-side policy; actors get them next batch.

        The collector reads its ``policy``'s weights before every batch anyway, so
        passing nothing (or the policy itself) is a no-op.
        """
        if kwargs:
            policy_or_weights = kwargs.get("weights", kwargs.get("policy", policy_or_weights))
        if policy_or_weights is None or policy_or_weights is self.policy:
            return
        if not isinstance(self.policy, nn.Module):
            raise TypeError("update_policy_weights_ needs a policy that is an nn.Module")
        if isinstance(policy_or_weights, (nn.Module, TensorDictModuleBase)):
            weights = TensorDict.from_module(policy_or_weights)
        elif isinstance(policy_or_weights, dict):
            weights = TensorDict(policy_or_weights).unflatten_keys(".")
        else:
            weights = policy_or_weights
        weights.data.to_module(self.policy)

    def shutdown(
        self,
        timeout: float | None = None,
        close_env: bool = True,
        raise_on_error: bool = True,
    ) -> None:
        """Close every actor's env workers, end the actors (and Ray, if started here)."""
        if self._closed:
            return
        self._closed = True
        ray = self._ray
        if self._actors:
            refs = [a.close.remote() for a in self._actors]
            # Actors that are already dead cannot close anything: ignore them.
            ray.wait(refs, num_returns=len(refs), timeout=10.0 if timeout is None else timeout)
            for actor in self._actors:
                try:
                    ray.kill(actor, no_restart=True)
                except Exception:  # noqa: BLE001, S110
                    pass
            self._actors = []
        if self._owns_ray and ray.is_initialized():
            ray.shutdown()

    def state_dict(self) -> OrderedDict:
        """Counters, the seed and every actor's snapshot (exact resume)."""
        return OrderedDict(
            frames=self._frames,
            batches=self._batches,
            next_group_id=self._next_group_id,
            seed=self._seed,
            num_actors=self.num_actors,
            trunk_frames=list(self._trunk_frames),
            snapshots=list(self._snapshots),
            restarts=self.restarts,
        )

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        """Restore :meth:`state_dict` (same number of actors); actors continue from it."""
        if int(state_dict["num_actors"]) != self.num_actors:
            raise ValueError(
                f"this state was saved with {state_dict['num_actors']} actors, "
                f"not {self.num_actors}: the actors' streams would differ"
            )
        self._frames = int(state_dict["frames"])
        self._batches = int(state_dict["batches"])
        self._next_group_id = int(state_dict["next_group_id"])
        self._seed = int(state_dict["seed"])
        self._trunk_frames = [int(x) for x in state_dict["trunk_frames"]]
        self._snapshots = list(state_dict["snapshots"])
        self.restarts = int(state_dict.get("restarts", 0))
        if self._actors:
            restores = [
                actor.restore.remote(snap)
                for actor, snap in zip(self._actors, self._snapshots, strict=True)
                if snap is not None
            ]
            self._ray.get(restores)

    def __len__(self) -> int:
        raise TypeError("the number of batches depends on where branches end: use total_frames")

    def __bool__(self) -> bool:
        # __len__ raises, and Python would call it for truth tests.
        return True

    def __enter__(self) -> RayGroupCollector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def __del__(self) -> None:
        # Best effort only: interpreter teardown may already have removed modules.
        try:
            self.shutdown()
        except Exception:  # noqa: S110
            pass

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_actors={self.num_actors}, group_size={self.group_size}, "
            f"horizon={self.horizon}, groups_per_batch={self.groups_per_batch}, "
            f"frames={self._frames}/{self.total_frames}, restarts={self.restarts})"
        )
