"""One interface over the three env shapes a branch rollout can run on.

A plain env (batch size ``()``) is one slot; a ``SerialEnv`` / ``ParallelEnv`` of W
workers is W slots. A slot is restored to a state with a partial reset
(``"_reset"`` mask, ``set_state=True``) and stepped with a partial step (``"_step"``
mask), so a slot whose branch has ended is never stepped again and never
auto-reset: its simulator stays at the branch's last state until it is restored.

States are read from the env's output when its workers return them
(``HighwayEnv(..., return_state=True)``: ``"state"`` after a reset,
``("next", "state")`` after a step), otherwise with ``get_state()``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_grpo.branching.keys import STATE
from torchrl_grpo.branching.workers import BranchParallelEnv
from torchrl_grpo.envs.core.errors import StateCorruptedError
from torchrl_grpo.envs.core.snapshot_batched import local_worker_env

logger = logging.getLogger(__name__)


class EnvSlots:
    """Restore, step and read the states of the slots of an env.

    Args:
        env: an unbatched env, or a batched env with batch size ``[W]``. Its
            workers must restore states through ``reset(..., set_state=True)``
            (a :class:`~torchrl_grpo.envs.SnapshotEnv`, optionally transformed).
    """

    def __init__(self, env: EnvBase) -> None:
        shape = tuple(env.batch_size)
        if len(shape) > 1:
            raise ValueError(f"branch rollouts need an env with batch size () or [W], got {shape}")
        if env.is_closed and hasattr(env, "start"):
            env.start()
        self.env = env
        self.batched = len(shape) == 1
        self.num_slots = shape[0] if self.batched else 1
        obs_keys = list(env.observation_spec.keys(True, True))
        # Workers built with return_state=True return their state as an observation.
        self.has_state = STATE in env.observation_spec.keys()
        self.obs_keys: list[NestedKey] = [k for k in obs_keys if not _under(k, STATE)]
        self.done_keys: list[NestedKey] = list(env.done_keys)
        self.action_keys: list[NestedKey] = list(env.action_keys)
        self.action_spec: TensorSpec = env.full_action_spec
        # What a step returns under "next" (the state apart: only when it is kept).
        self.next_keys: list[NestedKey] = [*self.obs_keys, *env.reward_keys, *self.done_keys]
        # A BranchParallelEnv, untransformed, restores and steps its workers directly
        # (transforms would be skipped otherwise).
        self._fast = isinstance(env, BranchParallelEnv) and env.branch_fast_paths_apply()
        # Branch rollouts on it run whole branches in the workers (worker_branches.py)
        # when the policy can go there, else lock-step with the policy here (lockstep.py).
        self.whole_branches = self._fast and env.whole_branches_apply()
        self._local: EnvBase | None = None
        self._warned_slow = False

    # ------------------------------------------------------------------ specs
    def check_states(self, states: TensorDictBase) -> None:
        """Raise a clear error unless ``states`` (batch ``[N]``) fit this env.

        Checked here, in the parent, before any worker sees them: a bad state would
        otherwise kill a ``ParallelEnv`` worker, or leave a ``SerialEnv`` half restored.
        The checks are the env's own (:meth:`~torchrl_grpo.envs.SnapshotEnv.validate_state`),
        run on a local copy of one worker.
        """
        device = next(iter(states.values(True, True))).device
        if has_batched_worlds(self.env):
            # A batched simulator's states live on its device and it checks them itself.
            self.env.validate_state(states.to(self.env.device))
            return
        if device.type != "cpu":
            raise StateCorruptedError(f"root states are on {device}; states live on the CPU")
        self._local_env().validate_state(states)

    # ------------------------------------------------------------------ actions
    def restore(
        self, slots: torch.Tensor, states: TensorDictBase, *, want_states: bool
    ) -> tuple[TensorDictBase, TensorDictBase | None]:
        """Restore ``states[i]`` into ``slots[i]``.

        Returns:
            The reset output rows of these slots (observations and done flags) and,
            when ``want_states``, the states the workers actually hold afterwards.
        """
        if not self.batched:
            out = self.env.reset(TensorDict({STATE: states[0]}), set_state=True)
            # A restore returns the tensordict it was given, state included (the envs
            # guarantee decode(encode(x)) == x): no read-back needed.
            rows = out.select(*self.obs_keys, *self.done_keys).unsqueeze(0)
            return rows, out.get(STATE).unsqueeze(0) if want_states else None
        if self._fast:
            keys = [*self.obs_keys, *self.done_keys]
            if want_states and self.has_state:
                keys.append(STATE)
            out = self.env.branch_restore(slots.tolist(), states, keys)
            snap = None
            if want_states:
                snap = out.pop(STATE) if self.has_state else self.read_all_states()[slots]
            return out, snap
        n = self.num_slots
        where = torch.zeros(n, dtype=torch.long)
        where[slots] = torch.arange(len(slots))
        mask = torch.zeros(n, dtype=torch.bool)
        mask[slots] = True
        # Rows of the slots left alone are not sent to their workers; any valid state
        # fills them so the tensordict matches the batched state spec.
        td = TensorDict({STATE: states[where], "_reset": mask.unsqueeze(-1)}, batch_size=[n])
        out = self.env.reset(td, set_state=True)
        snap = None
        if want_states:
            snap = out.get(STATE)[slots] if self.has_state else self.read_all_states()[slots]
        return out.select(*self.obs_keys, *self.done_keys)[slots], snap

    def step(
        self, td: TensorDictBase, active: torch.Tensor, *, want_states: bool = True
    ) -> TensorDictBase:
        """Step the ``active`` slots with the actions in ``td`` (batch ``[W]``).

        Returns:
            The step's ``"next"`` entries, batch ``[W]``: observations, reward and done
            flags, and, when ``want_states`` and the workers return them, ``"state"``.
            Rows of inactive slots are garbage.
        """
        if not self.batched:
            out = self.env.step(td[0].exclude("_step"))
            return out.get("next").unsqueeze(0)
        if self._fast:
            keys = self.next_keys + [STATE] if want_states and self.has_state else self.next_keys
            workers = active.nonzero().squeeze(-1).tolist()
            return self.env.branch_step(td, workers, keys)
        if bool(active.all()):
            return self.env.step(td).get("next")
        td.set("_step", active)
        out = self.env.step(td)
        out.pop("_step", None)
        return out.get("next")

    def next_states(self, nxt: TensorDictBase, rows: torch.Tensor | None) -> TensorDictBase:
        """The states after the step just taken, for the slots ``rows`` (``None``: all).

        ``nxt`` is what :meth:`step` returned, asked with ``want_states=True``.
        """
        snap = nxt.get(STATE, None)
        if snap is None:
            snap = self.read_all_states()
        return snap if rows is None else snap[rows]

    def reseed(self, states: TensorDictBase, seeds: list[int]) -> TensorDictBase:
        """``states`` ``[N]``, each with its simulator generator restarted from its seed."""
        return self._local_env().reseed_state(states, seeds)

    def _local_env(self) -> EnvBase:
        """The env itself, or a local copy of a batched env's first worker (cached).

        It holds a codec in this process, for validating and reseeding states.
        """
        if self._local is None:
            self._local = local_worker_env(self.env)
        return self._local

    # ------------------------------------------------------------------ states
    def read_all_states(self) -> TensorDictBase:
        """The current states of all slots, ``[W]`` (``[1]`` for a plain env)."""
        if not self.batched:
            return _get_state(self.env).unsqueeze(0)
        if not self._warned_slow:
            logger.warning(
                "reading worker states through env.get_state() (a pipe round trip per "
                "worker); build the workers with return_state=True (make_branch_env does, "
                "for highway-env) to ship them through shared memory"
            )
            self._warned_slow = True
        states: Sequence[TensorDictBase] = _get_state(self.env)
        return torch.stack(list(states))


def _under(key: NestedKey, root: str) -> bool:
    return key == root or (isinstance(key, tuple) and key[0] == root)


def _get_state(env: EnvBase) -> TensorDictBase | Sequence[TensorDictBase]:
    # TransformedEnv forwards unknown attributes to its base env; batched envs
    # dispatch the call to every worker and return the list of results.
    while isinstance(env, TransformedEnv) and not hasattr(type(env), "get_state"):
        env = env.base_env
    return env.get_state()


def has_batched_worlds(env: EnvBase) -> bool:
    """Whether ``env``'s batch rows are worlds it restores and steps together.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv
        >>> has_batched_worlds(TensorHighwayEnv(num_envs=2)), has_batched_worlds(HighwayEnv())
        (True, False)
    """
    # Read on the class: ParallelEnv forwards unknown attributes to its workers and
    # answers with their list of values.
    return getattr(type(env), "batched_worlds", False) is True and len(env.batch_size) == 1
