"""Branch rollouts on a batched simulator: every branch is a row of one batched rollout.

An env whose batch rows are independent worlds, restored and stepped together on its
own device (:class:`~torchrl_grpo.envs.TensorHighwayEnv`, marked by
``batched_worlds = True``), runs the N = R x G branches of a group rollout as rows of
one rollout: the roots' states are copied along the batch dimension, restored in one
``reset(..., set_state=True)``, and stepped in lockstep. A branch that ends keeps
being stepped with the others (its steps are masked out, and nothing resets it), so
the rollout's shapes never change; with N > B, the branches run in waves of B rows.

:func:`run_batched_branches` returns what the worker-slot engines return (a
:class:`~torchrl_grpo.branching.rollout_rows.BranchRun`), so
:func:`~torchrl_grpo.branching.branch_rollout` labels both the same way.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from torchrl_grpo.branching.action_checks import check_policy_actions
from torchrl_grpo.branching.keys import BRANCH, GROUP_ID, ROOT_STEP, STATE, STEP_COUNT
from torchrl_grpo.branching.rollout_rows import BranchRun, KeepStates, Policy

__all__ = ["run_batched_branches"]


def run_batched_branches(
    env: EnvBase,
    policy: Policy,
    states: TensorDictBase,
    horizon: int,
    *,
    group_id: torch.Tensor,
    branch: torch.Tensor,
    root_step: torch.Tensor,
    keep: KeepStates = "none",
    exploration_type: ExplorationType = ExplorationType.RANDOM,
    on_wave: Callable[[int], None] | None = None,
) -> BranchRun:
    """Run one branch per row of ``states`` (``[N]``, validated) for up to ``horizon`` steps.

    Args:
        env: an env with
            :func:`~torchrl_grpo.branching.env_slots.has_batched_worlds`, of batch ``[B]``.
        policy: reads the ``[B]`` tensordict (observations, ``group_id``, ``branch``,
            ``root_step``, ``step_count``) and writes ``"action"``.
        states: ``[N]`` start states of the branches.
        horizon: H, the most steps a branch takes.
        group_id: ``[N]`` int64, written for the policy.
        branch: ``[N]`` int64, likewise.
        root_step: ``[N]`` int64, likewise (``step_count`` is ``root_step + t``).
        keep: ``"all"`` keeps every step's state before and after it, ``"final"``
            each branch's last state.
        exploration_type: how the policy acts.
        on_wave: called with the number of branches of each wave (for progress).

    Returns:
        The :class:`~torchrl_grpo.branching.rollout_rows.BranchRun`: ``[N, H]`` data (zeros
        after each branch's end), mask, lengths, ended flags, final states.

    Example:
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> env = TensorHighwayEnv(num_envs=4, seed=0)
        >>> states = env.get_state()[:2].repeat_interleave(3, 0)  # 6 branches, 2 waves
        >>> slower = lambda td: td.set("action", torch.full((4,), 4))
        >>> n = torch.zeros(6, dtype=torch.int64)
        >>> run = run_batched_branches(env, slower, states, 5, group_id=n, branch=n, root_step=n)
        >>> run.data.batch_size, run.lengths.tolist()
        (torch.Size([6, 5]), [5, 5, 5, 5, 5, 5])
    """
    width = env.batch_size[0]
    n_branches = states.shape[0]
    device = env.device
    mask = torch.zeros(n_branches, horizon, dtype=torch.bool, device=device)
    lengths = torch.zeros(n_branches, dtype=torch.int64, device=device)
    ended = torch.zeros(n_branches, dtype=torch.bool, device=device)
    final = states.clone() if keep != "none" else None
    group_id, branch, root_step = (t.to(device) for t in (group_id, branch, root_step))
    waves: list[TensorDict] = []
    with torch.no_grad(), set_exploration_type(exploration_type):
        for start in range(0, n_branches, width):
            rows = torch.arange(start, min(start + width, n_branches), device=device)
            if on_wave is not None:
                on_wave(len(rows))
            waves.append(
                _wave(
                    env,
                    policy,
                    states,
                    rows,
                    horizon,
                    (group_id, branch, root_step),
                    keep,
                    mask,
                    lengths,
                    ended,
                    final,
                )  # fmt: skip
            )
    data = torch.cat(waves, 0)
    # Steps after a branch's end are zeros, as the worker-slot engine leaves them.
    data = data.apply(functools.partial(_zero_after_end, mask=mask))
    return BranchRun(data=data, mask=mask, lengths=lengths, ended=ended, final_states=final)


def _zero_after_end(leaf: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    keep = mask.view(*mask.shape, *[1] * (leaf.ndim - 2))
    return torch.where(keep, leaf, torch.zeros_like(leaf))


def _wave(env, policy, states, rows, horizon, labels, keep, mask, lengths, ended, final):
    """One wave of at most B branches, all rows stepped together; ``[len(rows), H]`` data."""
    width = env.batch_size[0]
    device = env.device
    group_id, branch, root_step = labels
    k = len(rows)
    # Pad a short last wave with copies of its first branch (masked out).
    pad = torch.cat([rows, rows[:1].expand(width - k)])
    live = torch.arange(width, device=device) < k
    td = env.reset(TensorDict({STATE: states[pad]}, batch_size=[width]), set_state=True)
    steps: list[TensorDict] = []
    for t in range(horizon):
        td = td.exclude(STATE)
        td.set(GROUP_ID, group_id[pad])
        td.set(BRANCH, branch[pad])
        td.set(ROOT_STEP, root_step[pad])
        td.set(STEP_COUNT, (root_step[pad] + t).unsqueeze(-1))
        out = policy(td)
        td = td if out is None else out
        check_policy_actions(td, env.full_action_spec, env.action_keys)
        before = env.get_state() if keep == "all" else None
        stepped = env.step(td)
        if keep == "all":
            stepped.set(STATE, before)
            stepped.set(("next", STATE), env.get_state())
        else:
            # An env built with return_state=True writes its state into every step: not
            # asked for here, it would only be stacked and masked with the data (and the
            # worker-slot engines do not return it either).
            stepped = stepped.exclude(("next", STATE))
        steps.append(stepped)
        mask[rows, t] = live[:k]
        done = stepped.get(("next", "done")).reshape(width)
        lengths[rows] = torch.where(live[:k], t + 1, lengths[rows])
        ended[rows] |= (live & done)[:k]
        if final is not None:
            last = (live & (done | (t + 1 == horizon)))[:k]
            if bool(last.any()):
                which = last.nonzero().squeeze(-1)
                final[rows[which]] = env.get_state()[which]
        live = live & ~done
        if not bool(live.any()):
            break
        td = step_mdp(stepped, keep_other=True, exclude_action=True)
    data = torch.stack(steps, 1)[:k]
    if data.shape[1] < horizon:
        filler = data[:, :1].apply(torch.zeros_like).expand(k, horizon - data.shape[1])
        data = torch.cat([data, filler.clone()], 1)
    return data
