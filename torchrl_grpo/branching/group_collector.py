"""GroupCollector: a TorchRL collector whose batches are branch groups ``[R, G, T]``."""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable
from typing import Literal

import torch
from tensordict import TensorDict
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.branch_env import shutdown_env
from torchrl_grpo.branching.collector_base import GroupCollectorBase
from torchrl_grpo.branching.continuation import ContinuationRoots, Selection
from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.keys import MASK, STATE
from torchrl_grpo.branching.rollout import RngMode, run_groups
from torchrl_grpo.branching.rollout_rows import Policy
from torchrl_grpo.branching.roots import EpisodeStartRoots, RootSource, TrunkRoots

logger = logging.getLogger(__name__)

RootKind = Literal["reset", "trunk", "continue"]

__all__ = ["GroupCollector", "RootKind"]


class GroupCollector(GroupCollectorBase):
    """Yields batches of branch groups, ``[R, G, T]``, until ``total_frames`` steps.

    Every batch branches G ways from R roots (see :func:`branch_rollout` for the
    keys of a batch). Group ids keep counting across batches, so ``group_id`` is
    unique over the whole collection. Roots come from ``roots``:

    - ``"reset"``: fresh episode starts (episode-level groups);
    - ``"trunk"``: decision points every ``decision_interval`` steps along policy
      trunks (vine-style; trunk steps are not part of the batches, see
      :attr:`trunk_frames`);
    - ``"continue"``: R live episodes that continue, after each batch, from their
      ``select``-ed branch (multi-turn); ended episodes are replaced by resets;
    - any :class:`~torchrl_grpo.branching.RootSource` (e.g.
      :class:`~torchrl_grpo.branching.StoredRoots` over stored trajectories).

    Frames count the steps branches took (``mask.sum()``), so a batch counts at
    most ``R * G * T`` frames. The policy runs in this process, on CPU, on the
    batched tensordict of the env's W workers; on a
    :class:`~torchrl_grpo.branching.BranchParallelEnv`, a policy that pickles runs in
    the workers instead, each with its copy, sent at every batch.

    The collector owns the env: :meth:`shutdown` closes it and its workers, and so
    does the end of the collection (``total_frames`` reached or the roots run out)
    and any error or interrupt raised while iterating. Leaving a ``for`` loop with
    ``break`` keeps it open. Use it as a context manager to close it on every path.

    Args:
        create_env_fn: the env (``ParallelEnv`` / ``SerialEnv`` / plain, see
            :func:`~torchrl_grpo.branching.make_branch_env`) or a callable building it.
        policy: the policy (a TensorDict module writing ``"action"``).
        group_size: G >= 2.
        horizon: T >= 1, steps per branch.
        groups_per_batch: R, roots per batch.
        total_frames: stop after this many branch steps (``-1``: never).
        roots: ``"reset"``, ``"trunk"``, ``"continue"`` or a ``RootSource``.
        decision_interval: K for ``roots="trunk"`` (default: ``horizon``).
        select: branch selection of ``roots="continue"``.
        temperature: softmax temperature of ``select="sampled"``.
        rng: ``"shared"`` or ``"per_branch"`` simulator randomness (see
            :func:`branch_rollout`).
        seed: seeds the episodes the root source resets, the branch selection and
            the per-branch simulator seeds. Without it, episode seeds are drawn from
            torch's global generator. The policy samples from torch's global
            generator too (in a ``BranchParallelEnv``'s workers, from seeds drawn
            from it): seed it with ``torch.manual_seed``.
        return_states: add ``"state"`` / ``("next", "state")`` to every step.
        set_truncated: see :func:`branch_rollout`.
        exploration_type: how the policy acts.

    Example:
        >>> from torchrl_grpo.branching import make_branch_env
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> env = make_branch_env("merge-v0", 2, backend="serial")
        >>> with GroupCollector(env, RandomPolicy(seed=0), group_size=2, horizon=3,
        ...                     groups_per_batch=2, total_frames=20, seed=0) as collector:
        ...     for batch in collector:
        ...         print(batch.batch_size, batch["group_id"][:, 0, 0].tolist())
        torch.Size([2, 2, 3]) [0, 1]
        torch.Size([2, 2, 3]) [2, 3]
    """

    def __init__(
        self,
        create_env_fn: EnvBase | Callable[[], EnvBase],
        policy: Policy,
        *,
        group_size: int,
        horizon: int,
        groups_per_batch: int,
        total_frames: int = -1,
        roots: RootKind | RootSource = "reset",
        decision_interval: int | None = None,
        select: Selection = "best",
        temperature: float = 1.0,
        rng: RngMode = "shared",
        seed: int | None = None,
        return_states: bool = False,
        set_truncated: bool = True,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
    ) -> None:
        try:
            super().__init__(policy, group_size, horizon, groups_per_batch, total_frames, rng)
            self.root_source = _make_source(
                roots, decision_interval or horizon, select, temperature
            )
        except Exception:
            # The collector owns a given env from the start: do not leave its workers running.
            if isinstance(create_env_fn, EnvBase):
                shutdown_env(create_env_fn)
            raise
        self.env: EnvBase = create_env_fn if isinstance(create_env_fn, EnvBase) else create_env_fn()
        self._closed = False
        self.rng = rng
        self.return_states = return_states
        self.set_truncated = set_truncated
        self.exploration_type = exploration_type
        self._seed = 0
        self._generator = torch.Generator()
        self._slots: EnvSlots | None = None
        if seed is not None:
            self.set_seed(seed)

    @property
    def trunk_frames(self) -> int:
        """Steps simulated on trunks to reach decision points (``roots="trunk"``)."""
        return int(getattr(self.root_source, "trunk_steps", 0))

    def _collect(self) -> TensorDict | None:
        if self._slots is None:
            self._slots = EnvSlots(self.env)
        source = self.root_source
        roots = source.next_roots(self.env, self.policy, self.groups_per_batch)
        if roots.shape[0] == 0:
            return None
        self._slots.check_states(roots.get(STATE))
        keep = "all" if self.return_states else ("final" if source.needs_final_states else "none")
        data, run = run_groups(
            self._slots,
            self.policy,
            roots,
            self.group_size,
            self.horizon,
            first_group_id=self._next_group_id,
            keep=keep,
            rng=self.rng,
            seed=self._seed,
            set_truncated=self.set_truncated,
            exploration_type=self.exploration_type,
        )
        n_roots = roots.shape[0]
        self._next_group_id += n_roots
        if source.needs_final_states:
            shape = (n_roots, self.group_size)
            source.observe(
                data,
                run.final_states.reshape(shape),
                run.ended.reshape(shape),
                generator=self._generator,
            )
        self._frames += int(data.get(MASK).sum())
        self._batches += 1
        return data

    # ------------------------------------------------------------------ TorchRL API
    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Seed the env's episodes, the branch selection and the per-branch seeds.

        Returns:
            The seed following the env's (TorchRL's convention).
        """
        self._seed = int(seed)
        self._generator.manual_seed(self._seed)
        self.root_source.set_seed(self._seed)
        return self.env.set_seed(seed, static_seed=static_seed)

    def _close(self, timeout: float, close_env: bool) -> None:
        if close_env:
            shutdown_env(self.env, timeout=timeout)

    def state_dict(self) -> OrderedDict:
        """Counters, the selection generator and the root source's state (exact resume)."""
        state = self.counters_state()
        state["generator"] = self._generator.get_state()
        state["root_source"] = self.root_source.state_dict()
        return state

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        """Restore :meth:`state_dict` (group ids continue where they stopped)."""
        self.load_counters_state(state_dict)
        self._generator.set_state(state_dict["generator"])
        self.root_source.load_state_dict(state_dict["root_source"])

    def _repr_extra(self) -> str:
        return f", roots={type(self.root_source).__name__}"


def _make_source(
    roots: RootKind | RootSource, every: int, select: Selection, temperature: float
) -> RootSource:
    if isinstance(roots, RootSource):
        return roots
    if roots == "reset":
        return EpisodeStartRoots()
    if roots == "trunk":
        return TrunkRoots(every)
    if roots == "continue":
        return ContinuationRoots(select, temperature=temperature)
    raise ValueError(f"roots must be 'reset', 'trunk', 'continue' or a RootSource, got {roots!r}")
