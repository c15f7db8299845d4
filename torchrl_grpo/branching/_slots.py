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
from collections.abc import Callable, Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase, TransformedEnv

from torchrl_grpo.branching.keys import STATE
from torchrl_grpo.envs import StateCorruptedError, StateMismatchError

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
        self._reference: TensorDictBase | None = None
        self._reseeder: Callable[[TensorDictBase, list[int]], TensorDictBase] | None = None
        self._warned_slow = False

    # ------------------------------------------------------------------ specs
    def reference_state(self) -> TensorDictBase:
        """A state of this env's config, read once from the first worker."""
        if self._reference is None:
            self._reference = self._read_all_states()[0].clone()
        return self._reference

    def check_states(self, states: TensorDictBase) -> None:
        """Raise a clear error unless ``states`` (batch ``[N]``) fit this env.

        Checked here, in the parent, before any worker sees them: a mismatched state
        would otherwise crash a ``ParallelEnv`` worker or fail on a shared-buffer copy.
        """
        reference = self.reference_state()
        expected = set(reference.keys(True, True))
        present = set(states.keys(True, True))
        if present != expected:
            missing = sorted(map(str, expected - present))[:5]
            extra = sorted(map(str, present - expected))[:5]
            raise StateMismatchError(
                "the root states do not have this env's state layout (captured from another "
                f"scenario or env?): missing {missing}, unexpected {extra}"
            )
        batch = states.batch_dims
        for key in expected:
            want, got = reference.get(key), states.get(key)
            if got.shape[batch:] != want.shape or got.dtype != want.dtype:
                raise StateMismatchError(
                    f"root state entry {key!r} has shape {tuple(got.shape[batch:])} and dtype "
                    f"{got.dtype}; this env's states have {tuple(want.shape)} and {want.dtype} "
                    "(captured from another scenario, config or padding?)"
                )
        for key in expected:
            if isinstance(key, tuple) and "fingerprint" in key:
                want = reference.get(key)
                got = states.get(key)
                bad = (got != want).reshape(got.shape[:batch].numel(), -1).any(-1)
                if bad.any():
                    first = int(bad.nonzero()[0])
                    raise StateMismatchError(
                        f"root state {first} was captured from another config: its {key!r} is "
                        f"{got.reshape(-1)[first].item()}, this env's is {want.item()}"
                    )
        device = states.get(next(iter(expected))).device
        if device.type != "cpu":
            raise StateCorruptedError(f"root states are on {device}; states live on the CPU")

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
        n = self.num_slots
        where = torch.zeros(n, dtype=torch.long)
        where[slots] = torch.arange(len(slots))
        mask = torch.zeros(n, dtype=torch.bool)
        mask[slots] = True
        # Rows of the slots left alone are not sent to their workers; any valid state
        # fills them so the tensordict matches the batched state spec.
        td = TensorDict(
            {STATE: states[where], "_reset": mask.unsqueeze(-1)}, batch_size=[n]
        )
        out = self.env.reset(td, set_state=True)
        snap = None
        if want_states:
            snap = out.get(STATE)[slots] if self.has_state else self._read_all_states()[slots]
        return out.select(*self.obs_keys, *self.done_keys)[slots], snap

    def step(self, td: TensorDictBase, active: torch.Tensor) -> TensorDictBase:
        """Step the ``active`` slots with the actions in ``td`` (batch ``[W]``).

        Returns ``td`` with its ``"next"`` entry; rows of inactive slots are garbage.
        """
        if not self.batched:
            out = self.env.step(td[0].exclude("_step"))
            return out.unsqueeze(0)
        if bool(active.all()):
            return self.env.step(td)
        td.set("_step", active)
        out = self.env.step(td)
        out.pop("_step", None)
        return out

    def next_states(self, td: TensorDictBase, slots: torch.Tensor) -> TensorDictBase:
        """The states after the step just taken, for ``slots``."""
        snap = td.get(("next", STATE), None)
        if snap is not None:
            return snap[slots]
        return self._read_all_states()[slots]

    def reseed(self, states: TensorDictBase, seeds: list[int]) -> TensorDictBase:
        """``states`` ``[N]``, each with its simulator generator restarted from its seed.

        Runs :meth:`~torchrl_grpo.envs.SnapshotEnv.reseed_state` of the env, or of its
        first worker: in one call for the whole batch, as a worker is a pipe round
        trip away (codecs do not pickle, so the parent cannot hold one).
        """
        if self._reseeder is None:
            self._reseeder = _reseeder(self.env)
        return self._reseeder(states, seeds)

    # ------------------------------------------------------------------ states
    def _read_all_states(self) -> TensorDictBase:
        if not self.batched:
            return _get_state(self.env).unsqueeze(0)
        if not self._warned_slow and self._reference is not None:
            logger.warning(
                "reading worker states through env.get_state() (a pipe round trip per "
                "worker); build the env with make_branch_env(..., snapshots=True) (workers "
                "with return_state=True) to ship them through shared memory"
            )
            self._warned_slow = True
        states: Sequence[TensorDictBase] = _get_state(self.env)
        return torch.stack(list(states))


def _under(key: NestedKey, root: str) -> bool:
    return key == root or (isinstance(key, tuple) and key[0] == root)


def _base(env: EnvBase) -> EnvBase:
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env


def _reseeder(env: EnvBase) -> Callable[[TensorDictBase, list[int]], TensorDictBase]:
    base = _base(env)
    if not base.batch_size:
        return base.reseed_state
    # A view on the first worker: a batched env would run the call on every worker.
    first = base[0]

    def reseed(states: TensorDictBase, seeds: list[int]) -> TensorDictBase:
        try:
            return first.reseed_state(states, seeds)[0]
        except (EOFError, ConnectionError) as err:
            # A ParallelEnv worker that raises dies; the parent only sees its pipe close.
            raise RuntimeError(
                "the first worker failed to reseed the branch states and stopped (its "
                "codec may not implement StateCodec.reseed; run a SerialEnv to see the "
                "worker's error)"
            ) from err

    return reseed


def _get_state(env: EnvBase) -> TensorDictBase | Sequence[TensorDictBase]:
    # TransformedEnv forwards unknown attributes to its base env; batched envs
    # dispatch the call to every worker and return the list of results.
    while isinstance(env, TransformedEnv) and not hasattr(type(env), "get_state"):
        env = env.base_env
    return env.get_state()
