"""Whole branches in a branch worker: restore, then policy and step until the branch ends.

The part of a :class:`~torchrl_grpo.branching.BranchParallelEnv` worker that runs the
jobs of :func:`~torchrl_grpo.branching.worker_branches.run_whole_branches`. At the start
of a rollout the parent sends a ``"setup"`` message with the packed policy
(:mod:`~torchrl_grpo.branching.policy_transport`) and what the rollout keeps; then one
``"branch"`` message per branch. The worker restores the branch's start state, and
for ``t < H`` builds the policy's input as the lock-step engine does (observations,
done flags, ``group_id``, ``branch``, ``root_step``, ``step_count = root_step + t``,
a batch of one row), runs its copy of the policy under the rollout's exploration
type, checks the action, and steps, until ``done`` or ``H`` steps. It answers once
per branch with the branch's rows stacked, ``[T, ...]`` numpy arrays.

Messages come through TorchRL's generic attribute call (the worker calls
``env.branch_runs(message)`` and answers ``("branch_runs_done", answer)``). An
exception is answered as ``("error", pickled exception or None, traceback)``: the
worker stays alive, and the parent raises the exception itself.
"""

from __future__ import annotations

import pickle
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching.action_checks import check_policy_actions
from torchrl_grpo.branching.keys import BRANCH, GROUP_ID, ROOT_STEP, STATE, STEP_COUNT
from torchrl_grpo.branching.pipe_arrays import (
    STATE_ALWAYS,
    Arrays,
    from_arrays,
    step_keeping_state,
    to_arrays,
)
from torchrl_grpo.branching.policy_transport import PackedPolicy, PolicyCopy

__all__ = ["BranchRunner", "RolloutSetup"]

# Entries of the policy's td that are not per-step data (as the lock-step engine skips them).
_SKIP = ((STATE,), ("next",), ("_step",))


@dataclass
class RolloutSetup:
    """What a worker needs to run a rollout's branches.

    Attributes:
        policy: the packed policy.
        input_keys: the observation and done entries the policy reads.
        next_keys: the entries of a step's ``"next"`` to send back.
        state_mode: ``STATE_NEVER``, ``STATE_AT_END`` (final states) or
            ``STATE_ALWAYS`` (every step's state before and after it).
        horizon: H, the most steps a branch takes.
        exploration_type: how the policy acts.
    """

    policy: PackedPolicy
    input_keys: list[NestedKey]
    next_keys: list[NestedKey]
    state_mode: int
    horizon: int
    exploration_type: ExplorationType


class BranchRunner:
    """Runs whole branches on a worker's env with the worker's copy of the policy.

    Args:
        env: the worker's env.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.branching.pipe_arrays import STATE_AT_END
        >>> from torchrl_grpo.branching.policy_transport import pack_policy
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> env = HighwayEnv("merge-v0", return_state=True)
        >>> runner = BranchRunner(env)
        >>> keys = ["observation", "done", "terminated", "truncated"]
        >>> setup = RolloutSetup(pack_policy(RandomPolicy(seed=0)), keys, [*keys, "reward"],
        ...                      STATE_AT_END, 3, ExplorationType.RANDOM)
        >>> runner(("setup", setup))
        ('ready',)
        >>> state = to_arrays(env.reset().get("state"))
        >>> kind, answer = runner(("branch", 0, state, (0, 0, 0)))
        >>> answer["length"], answer["root"][("action",)].shape, answer["final"] is not None
        (3, (3,), True)
    """

    def __init__(self, env: EnvBase) -> None:
        self.env = env
        self.setup: RolloutSetup | None = None
        self.policy: PolicyCopy | None = None

    def __call__(self, message: tuple) -> tuple:
        """Answer ``("setup", RolloutSetup)`` or ``("branch", index, state, ids)``.

        Answers: ``("ready",)``; ``("unusable", traceback)`` when the policy does not
        unpickle here (the parent then runs the rollout itself); ``("branch", rows)``;
        ``("error", pickled exception, traceback)``.
        """
        try:
            if message[0] == "setup":
                self.setup, self.policy = None, None
                try:
                    policy = PolicyCopy(message[1].policy)
                except Exception:  # noqa: BLE001 - the parent falls back
                    return ("unusable", traceback.format_exc())
                self.setup, self.policy = message[1], policy
                return ("ready",)
            if self.policy is None:
                raise RuntimeError("a branch job came before a usable rollout setup")
            return ("branch", self._branch(*message[1:]))
        except Exception as err:
            return ("error", _dumps(err), traceback.format_exc())

    def _branch(self, index: int, state: Arrays, ids: tuple[int, int, int]) -> dict[str, Any]:
        setup, policy, env = self.setup, self.policy, self.env
        policy.seed_branch(index)
        out = env.reset(TensorDict({STATE: from_arrays([state], batch=False)}), set_state=True)
        keep_all = setup.state_mode == STATE_ALWAYS
        before = out.get(STATE) if keep_all else None
        labels = {GROUP_ID: torch.tensor([ids[0]]), BRANCH: torch.tensor([ids[1]])}
        labels[ROOT_STEP] = torch.tensor([ids[2]])
        td = _policy_input(out, setup.input_keys, labels, ids[2])
        spec, action_keys = env.full_action_spec, env.action_keys
        rows: list[TensorDictBase] = []
        nexts: list[TensorDictBase] = []
        states: list[tuple[TensorDictBase, TensorDictBase]] = []
        snap, done = None, False
        with torch.no_grad(), set_exploration_type(setup.exploration_type):
            for t in range(setup.horizon):
                result = policy(td)
                td = td if result is None else result
                check_policy_actions(td, spec, action_keys, per_worker=True)
                rows.append(td)
                action = TensorDict({k: td.get(k)[0] for k in action_keys})
                last = t + 1 >= setup.horizon
                nxt, snap = step_keeping_state(env, action, setup.state_mode, last)
                nexts.append(nxt)
                if keep_all:
                    states.append((before, snap))
                    before = snap
                done = bool(nxt.get("done").any())
                if done or last:
                    break
                td = _policy_input(nxt, setup.input_keys, labels, ids[2] + t + 1)
        root_keys = [k for k in rows[0].keys(True, True) if not _skipped(k)]
        return {
            "index": index,
            "length": len(rows),
            "ended": done,
            "root": {_as_tuple(k): torch.cat([r.get(k) for r in rows]).numpy() for k in root_keys},
            "next": _stack(nexts, setup.next_keys),
            "before": _stack([s[0] for s in states]) if keep_all else None,
            "after": _stack([s[1] for s in states]) if keep_all else None,
            "final": None if snap is None else to_arrays(snap),
        }


def _policy_input(
    out: TensorDictBase, keys: Sequence[NestedKey], labels: dict[str, torch.Tensor], step: int
) -> TensorDict:
    """The policy's input after a restore or step, a batch of one row.

    ``keys`` of ``out`` (observations, done flags), then the branch's ``labels``
    (``group_id``, ``branch``, ``root_step``) and ``step_count``, in the order the
    lock-step engine writes them.
    """
    source = {k: out.get(k).unsqueeze(0) for k in keys}
    source.update(labels)
    source[STEP_COUNT] = torch.tensor([[step]])
    return TensorDict(source, batch_size=[1])


def _stack(tds: Sequence[TensorDictBase], keys: Sequence[NestedKey] | None = None) -> Arrays:
    """``[T, ...]`` numpy arrays of ``keys`` (default: all leaves) of ``T`` tensordicts."""
    if keys is None:
        keys = list(tds[0].keys(True, True))
    return {_as_tuple(k): torch.stack([td.get(k) for td in tds]).numpy() for k in keys}


def _skipped(key: NestedKey) -> bool:
    path = _as_tuple(key)
    return any(path[: len(s)] == s for s in _SKIP)


def _dumps(err: BaseException) -> bytes | None:
    """The pickled exception, if it pickles and unpickles (the parent re-raises it)."""
    try:
        blob = pickle.dumps(err)
        pickle.loads(blob)
    except Exception:  # noqa: BLE001 - the parent raises a RuntimeError instead
        return None
    return blob


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return key if isinstance(key, tuple) else (key,)
