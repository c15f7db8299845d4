"""Branch rollouts: G rollouts of a policy from each of R root states, as one ``[R, G, T]``."""

from __future__ import annotations

from numbers import Integral
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.dispatch import run_on
from torchrl_grpo.branching.env_slots import EnvSlots, has_batched_worlds
from torchrl_grpo.branching.keys import (
    BRANCH,
    BRANCH_RETURN,
    GROUP_ID,
    MASK,
    ROOT_STEP,
    STATE,
    STEP_COUNT,
    TRAJ_IDS,
)
from torchrl_grpo.branching.rollout_rows import BranchRun, Policy
from torchrl_grpo.branching.root_builders import as_roots
from torchrl_grpo.branching.seeding import branch_seed

RngMode = Literal["shared", "per_branch"]

__all__ = ["RngMode", "branch_rollout", "final_states"]


def check_group_args(group_size: int, horizon: int, rng: str) -> None:
    """Validate the arguments every group function shares."""
    if not _is_int(group_size) or group_size < 2:
        raise ValueError(
            f"group_size must be an int >= 2 (a group compares branches), got {group_size!r}"
        )
    if not _is_int(horizon) or horizon < 1:
        raise ValueError(f"horizon must be an int >= 1, got {horizon!r}")
    if rng not in ("shared", "per_branch"):
        raise ValueError(f"rng must be 'shared' or 'per_branch', got {rng!r}")


def _is_int(value: object) -> bool:
    return isinstance(value, Integral) and not isinstance(value, bool)


def run_groups(
    slots: EnvSlots,
    policy: Policy,
    roots: TensorDict,
    group_size: int,
    horizon: int,
    *,
    first_group_id: int,
    keep: Literal["none", "final", "all"],
    rng: RngMode,
    seed: int,
    set_truncated: bool,
    exploration_type: ExplorationType,
) -> tuple[TensorDict, BranchRun]:
    """Run validated roots; return the ``[R, G, T]`` data and the engine's ``[R * G]`` run."""
    n_roots, g, horizon = roots.shape[0], int(group_size), int(horizon)
    batched = has_batched_worlds(slots.env)
    device = slots.env.device if batched else torch.device("cpu")
    group_id = (first_group_id + torch.arange(n_roots, device=device)).repeat_interleave(g)
    branch = torch.arange(g, device=device).repeat(n_roots)
    root_step = roots.get(ROOT_STEP).to(device).repeat_interleave(g)
    states = roots.get(STATE).to(device)[torch.arange(n_roots, device=device).repeat_interleave(g)]
    if rng == "per_branch":
        pairs = zip(group_id.tolist(), branch.tolist(), strict=True)
        seeds = [branch_seed(seed, gid, b) for gid, b in pairs]
        states = slots.reseed(states, seeds)
    # A batched simulator runs the R x G branches as rows of one rollout on its device;
    # other envs run them on their worker slots.
    run = run_on(
        slots,
        policy,
        states,
        horizon,
        group_id=group_id,
        branch=branch,
        root_step=root_step,
        keep=keep,
        exploration_type=exploration_type,
    )
    data = run.data
    mask = run.mask
    steps = torch.arange(horizon, device=device)
    data.set(GROUP_ID, group_id.unsqueeze(-1).expand(-1, horizon).clone())
    data.set(BRANCH, branch.unsqueeze(-1).expand(-1, horizon).clone())
    data.set(ROOT_STEP, root_step.unsqueeze(-1).expand(-1, horizon).clone())
    data.set(STEP_COUNT, (root_step.unsqueeze(-1) + steps).unsqueeze(-1))
    data.set(MASK, mask)
    data.set(TRAJ_IDS, (group_id * g + branch).unsqueeze(-1).expand(-1, horizon).clone())
    reward = data.get(("next", "reward"))
    returns = (reward * mask.view(*mask.shape, *([1] * (reward.dim() - 2)))).sum(1, keepdim=True)
    data.set(BRANCH_RETURN, returns.expand_as(reward).clone())
    if set_truncated:
        _mark_horizon_ends(data, run)
    return data.reshape(n_roots, g, horizon), run


def _mark_horizon_ends(data: TensorDict, run: BranchRun) -> None:
    """Flag the last step of branches cut by the horizon as truncated and done.

    TorchRL collectors do the same with ``set_truncated=True``: every trajectory then
    ends with ``done``, which trajectory splitters and ``MCAdvantage`` rely on.
    """
    cut = (~run.ended).nonzero().squeeze(-1)
    last = run.lengths[cut] - 1
    for key in (("next", "truncated"), ("next", "done")):
        if key in data.keys(True):
            flags = data.get(key)
            flags[cut, last] = True


def branch_rollout(
    env: EnvBase,
    policy: Policy,
    roots: TensorDictBase,
    group_size: int,
    horizon: int,
    *,
    return_states: bool = False,
    rng: RngMode = "shared",
    seed: int = 0,
    first_group_id: int = 0,
    set_truncated: bool = True,
    exploration_type: ExplorationType = ExplorationType.RANDOM,
) -> TensorDict:
    """Roll out ``group_size`` branches of ``policy`` from each root, ``horizon`` steps at most.

    The R x G branches run on the env's slots (W workers of a ``ParallelEnv`` /
    ``SerialEnv``, or one plain env), W at a time: a slot takes the next branch as
    soon as its branch ends. A branch ends after ``horizon`` steps or when the env
    says ``done``; the steps after its end are zeros with ``mask == False`` (no
    worker is stepped past a branch's end, so nothing is auto-reset).

    The output, ``[R, G, T]`` with ``T = horizon``, holds what a TorchRL collector
    gives per step (observations, ``action`` and whatever the policy wrote, e.g.
    ``action_log_prob``; ``("next", ...)`` with ``reward``, ``done``,
    ``terminated``, ``truncated``) plus:

    - ``group_id`` (int64): ``first_group_id + r``, the key
      :class:`~torchrl.objectives.llm.MCAdvantage` groups by;
    - ``branch`` (int64), ``root_step`` (int64), ``step_count`` (``[..., 1]``);
    - ``mask`` (bool): the step was taken;
    - ``branch_return`` (``[..., 1]``): the sum of the branch's valid rewards;
    - ``("collector", "traj_ids")``: a unique id per branch;
    - with ``return_states``: ``"state"`` and ``("next", "state")``, the simulator
      state before and after every step (``state[r, g, 0]`` is the state the branch
      was restored to: the root, or its reseeded copy with ``rng="per_branch"``).

    Branches from one state differ only through the policy's samples: highway-env
    draws no random numbers while stepping, except intersection-v0, which spawns
    traffic at random. ``rng="per_branch"`` restarts each branch's simulator
    generator from :func:`~torchrl_grpo.branching.branch_seed` ``(seed, group_id,
    branch)`` (with :meth:`~torchrl_grpo.envs.SnapshotEnv.reseed_state`): use it
    when the env's own randomness should vary within a group (intersection-v0
    traffic); keep ``"shared"`` (the default) when the group should measure the
    policy's choices only, with the same traffic for every branch.

    Args:
        env: the env running the branches: ``ParallelEnv`` / ``SerialEnv`` of
            :class:`~torchrl_grpo.envs.HighwayEnv` (see
            :func:`~torchrl_grpo.branching.make_branch_env`) or a plain one.
        policy: a TensorDict module / callable writing ``"action"``; it reads a
            ``[W]`` tensordict (``[1]`` on a plain env, and in the workers of a
            :class:`~torchrl_grpo.branching.BranchParallelEnv`, which run whole
            branches with copies of a policy that pickles) holding the observations
            and ``group_id``, ``branch``, ``root_step``, ``step_count``.
        roots: roots ``[R]`` (see :mod:`~torchrl_grpo.branching.roots`), or states.
        group_size: G >= 2, branches per root.
        horizon: H >= 1, the most steps a branch takes.
        return_states: keep the state before and after every step.
        rng: ``"shared"`` or ``"per_branch"`` (see above).
        seed: mixed into the per-branch seeds (``rng="per_branch"``).
        first_group_id: the group id of the first root; use a running counter to
            keep ids unique across calls (as :class:`GroupCollector` does).
        set_truncated: flag ``("next", "truncated")`` and ``("next", "done")`` on
            the last step of branches cut by the horizon, so that every branch ends
            with ``done`` (what ``MCAdvantage`` and trajectory splitters need).
        exploration_type: how the policy acts (sampling by default: groups need it).

    Returns:
        The ``[R, G, H]`` tensordict.

    Raises:
        ValueError: G < 2, H < 1, a policy output that does not fit the action spec.
        StateMismatchError: roots from another scenario or config.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> from torchrl_grpo.branching import reset_roots
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> roots = reset_roots(env, 2, seed=0)
        >>> data = branch_rollout(env, RandomPolicy(seed=0), roots, group_size=3, horizon=4)
        >>> data.batch_size, data["group_id"][:, 0, 0].tolist()
        (torch.Size([2, 3, 4]), [0, 1])
    """
    check_group_args(group_size, horizon, rng)
    slots = EnvSlots(env)
    roots = as_roots(roots)
    slots.check_states(roots.get(STATE))
    data, _ = run_groups(
        slots,
        policy,
        roots,
        group_size,
        horizon,
        first_group_id=first_group_id,
        keep="all" if return_states else "none",
        rng=rng,
        seed=seed,
        set_truncated=set_truncated,
        exploration_type=exploration_type,
    )
    return data


def final_states(data: TensorDictBase) -> TensorDictBase:
    """The state after each branch's last valid step: ``[R, G]`` from ``[R, G, T]``.

    Needs data rolled out with ``return_states=True``. Restoring a final state
    continues the branch exactly where it stopped.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv, states_equal
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> from torchrl_grpo.branching import reset_roots
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> data = branch_rollout(env, RandomPolicy(seed=0), reset_roots(env, 1, seed=0), 2, 3,
        ...                       return_states=True)
        >>> final_states(data).batch_size
        torch.Size([1, 2])
    """
    key = ("next", STATE)
    if key not in data.keys(True):
        raise KeyError("final_states needs data from branch_rollout(..., return_states=True)")
    last = (data.get(MASK).sum(-1) - 1).clamp(min=0)
    states = data.get(key)
    flat = states.reshape(-1, states.shape[-1])
    return flat[torch.arange(flat.shape[0]), last.reshape(-1)].reshape(last.shape)
