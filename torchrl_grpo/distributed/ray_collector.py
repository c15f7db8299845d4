"""RayGroupCollector: branch groups collected by Ray actors, gathered by the learner."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.collector_base import GroupCollectorBase
from torchrl_grpo.branching.continuation import Selection
from torchrl_grpo.branching.group_collector import RootKind
from torchrl_grpo.branching.keys import MASK
from torchrl_grpo.branching.rollout import RngMode
from torchrl_grpo.branching.roots import RootSource
from torchrl_grpo.distributed.actor_pool import ActorPool, split_groups
from torchrl_grpo.distributed.ray_setup import init_ray, require_ray

__all__ = ["RayGroupCollector", "split_groups"]


class RayGroupCollector(GroupCollectorBase):
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
        super().__init__(policy, group_size, horizon, groups_per_batch, total_frames, rng)
        self._owns_ray = False
        self._ray = require_ray()
        if isinstance(env_factory, EnvBase) or not callable(env_factory):
            raise TypeError(
                "env_factory must be a picklable callable building the env in the actor "
                "(e.g. functools.partial(make_branch_env, scenario, W)), not an env"
            )
        if max_restarts < 0:
            raise ValueError(f"max_restarts must be >= 0, got {max_restarts}")
        groups_per_actor = split_groups(groups_per_batch, num_actors)
        if isinstance(roots, Sequence) and not isinstance(roots, str):
            if len(roots) != num_actors:
                raise ValueError(f"got {len(roots)} root sources for {num_actors} actors")
            roots_per_actor = list(roots)
        else:
            roots_per_actor = [roots] * num_actors
        self.env_factory = env_factory
        self.num_actors = num_actors
        self.groups_per_actor = groups_per_actor
        options = {"num_cpus": float(num_cpus_per_actor), **(actor_options or {})}
        if memory_per_actor is not None:
            options["memory"] = int(memory_per_actor)
        # Seeds drawn here (not in the actors) keep an unseeded run reproducible
        # under torch.manual_seed, like the local collector.
        seed = int(torch.randint(0, 2**31 - 1, ())) if seed is None else int(seed)
        self._pool = ActorPool(
            self._ray,
            env_factory,
            policy,
            roots_per_actor,
            dict(
                group_size=group_size,
                horizon=horizon,
                decision_interval=decision_interval,
                select=select,
                temperature=temperature,
                rng=rng,
                return_states=return_states,
                set_truncated=set_truncated,
                exploration_type=exploration_type,
            ),
            groups_per_actor,
            seed,
            options,
            num_threads=num_threads,
            max_restarts=max_restarts,
            wait_timeout=wait_timeout,
        )
        self._owns_ray = init_ray(**(ray_init or {}))
        self._closed = False
        try:
            self._pool.check_resources()
        except Exception:
            self.shutdown()
            raise

    @property
    def trunk_frames(self) -> int:
        """Trunk steps simulated by all actors (``roots="trunk"``)."""
        return int(sum(self._pool.trunk_frames))

    @property
    def actors(self) -> list[Any]:
        """The live Ray actor handles, one per actor index (tests kill them)."""
        return list(self._pool.actors)

    @property
    def restarts(self) -> int:
        """Actors replaced so far (each after a death)."""
        return self._pool.restarts

    @property
    def actor_options(self) -> dict[str, Any]:
        """The ``ray.remote`` options of the actors (``num_cpus``, ``memory``, ...)."""
        return self._pool.actor_options

    def _weights(self) -> Any:
        if not isinstance(self.policy, nn.Module):
            return None
        # One copy in the object store per batch, read by every actor.
        return self._ray.put(TensorDict.from_module(self.policy).data.clone())

    def _collect(self) -> TensorDict | None:
        first_ids, offset = [], self._next_group_id
        for n in self.groups_per_actor:
            first_ids.append(offset)
            offset += n
        results = self._pool.gather(self._weights(), first_ids, batch=self._batches)
        parts = [r.data for r in results if r.data is not None and r.data.shape[0] > 0]
        if not parts:
            return None
        data = torch.cat(parts) if len(parts) > 1 else parts[0]
        self._pool.keep(results)
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
        self._pool.set_seed(seed)
        return self._pool.seed

    def _close(self, timeout: float, close_env: bool) -> None:
        """Close every actor's env workers, end the actors (and Ray, if started here)."""
        self._pool.close(timeout)
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()

    def state_dict(self) -> OrderedDict:
        """Counters, the seed and every actor's snapshot (exact resume)."""
        state = self.counters_state()
        state["num_actors"] = self.num_actors
        state.update(self._pool.state_dict())
        return state

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        """Restore :meth:`state_dict` (same number of actors); actors continue from it."""
        if int(state_dict["num_actors"]) != self.num_actors:
            raise ValueError(
                f"this state was saved with {state_dict['num_actors']} actors, "
                f"not {self.num_actors}: the actors' streams would differ"
            )
        self.load_counters_state(state_dict)
        self._pool.load_state_dict(state_dict)

    def _repr_extra(self) -> str:
        return f", num_actors={self.num_actors}, restarts={self.restarts}"
