"""Group-relative advantage: returns normalised within groups of branches sharing a root."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Literal, get_args

import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_grpo.objectives._segments import (
    check_distinct_trajectories,
    positions_in_segments,
    segment_mean_std,
    segment_sum,
    trajectory_index,
)

__all__ = ["Baseline", "GroupRelativeAdvantage", "Returns", "RewardScaling"]

#: A branch's return (``"branch"``) or each step's reward-to-go (``"step"``).
Returns = Literal["branch", "step"]
#: The group mean (GRPO, ``"mean"``) or the mean of the other members (RLOO, ``"loo"``).
Baseline = Literal["mean", "loo"]
#: What the centred returns are divided by: the group's std, the batch's, or nothing.
RewardScaling = Literal["group", "batch", "none"]

# Below this, gamma ** position underflows float64 and the reward-to-go
# rescaling (which divides by gamma ** position) would return inf / NaN.
_MIN_DISCOUNT = 1e-250


class GroupRelativeAdvantage(TensorDictModuleBase):
    """Group-relative advantage (GRPO, RLOO, Dr. GRPO) for branch-group tensordicts.

    Reads a group of G branches per root (``group_id`` shared by the branches of a
    root, ``branch`` their index) and writes an ``"advantage"`` entry of shape
    ``[*batch, 1]``, like TorchRL's advantage modules. The layout may be
    ``[R, G, T]``, ``[N, T]`` or flat ``[B]``: trajectories are identified by the
    pair ``(group_id, branch)``, never by the shape. Within a trajectory, steps must
    appear in time order in the row-major flattening of the batch, which holds for
    all three layouts and for any concatenation of whole trajectories.

    Steps whose ``mask`` is ``False`` (after the branch ended) are ignored: their
    reward may be anything, their advantage is 0.

    Returns are either per branch (``returns="branch"``: the discounted sum of the
    branch's rewards, the same advantage for each of its steps, DeepSeekMath's
    outcome supervision) or per step (``returns="step"``: the discounted
    reward-to-go of each step, normalised among the group's branches at the same
    step index, i.e. the steps reached after the same number of actions from the
    shared root).

    The normalisation of a return ``x`` in a group is ``(x - baseline) / (scale +
    eps)``, the formula of TRL's ``GRPOTrainer``:

    - ``baseline="mean"``: the group mean (GRPO); ``"loo"``: the mean of the other
      members (RLOO).
    - ``scale_rewards="group"``: the group's std (unbiased, as ``torch.std``);
      ``"batch"``: the std of all returns in the batch; ``"none"``: no division
      (Dr. GRPO), and ``eps`` is not added.

    A group whose returns are all equal (or, for per-step groups, that has a single
    member) gets exactly zero advantage. A root group with a single branch, a
    missing key, or a NaN reward on a valid step raises a ``ValueError`` naming the
    key or the group ids; so does a ``(group_id, branch)`` pair held by two
    trajectories (two rows, or two separate runs of a flat batch), as
    ``torch.cat`` of two ``branch_rollout`` outputs that both start at
    ``first_group_id=0`` gives.

    The module returns the tensordict it was given, so it can run before the loss
    or on writes to a replay buffer: ``rb.append_transform(module, invert=True)``.

    Args:
        returns: ``"branch"`` or ``"step"`` (see above).
        baseline: ``"mean"`` or ``"loo"``.
        scale_rewards: ``"group"``, ``"batch"`` or ``"none"`` (TRL's option name).
        gamma: discount of the returns; 1.0 sums the rewards.
        eps: added to the std before dividing, as TRL does.

    Keys (change them with :meth:`set_keys`): ``group_id`` (``"group_id"``),
    ``branch`` (``"branch"``), ``reward`` (``("next", "reward")``), ``mask``
    (``"mask"``), ``advantage`` (``"advantage"``, written).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.objectives import GroupRelativeAdvantage
        >>> R, G, T = 1, 3, 2
        >>> rewards = torch.tensor([[[0.0, 1.0], [1.0, 1.0], [1.0, 2.0]]]).unsqueeze(-1)
        >>> td = TensorDict(
        ...     {
        ...         "group_id": torch.zeros(R, G, T, dtype=torch.long),
        ...         "branch": torch.arange(G).view(1, G, 1).expand(R, G, T),
        ...         "mask": torch.ones(R, G, T, dtype=torch.bool),
        ...         ("next", "reward"): rewards,
        ...     },
        ...     batch_size=[R, G, T],
        ... )
        >>> adv = GroupRelativeAdvantage(eps=0.0)(td)["advantage"]
        >>> adv.shape
        torch.Size([1, 3, 2, 1])
        >>> adv[0, :, 0, 0]
        tensor([-1.,  0.,  1.])
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read and written by :class:`GroupRelativeAdvantage`.

        Attributes:
            group_id: integer id shared by the branches of one root.
            branch: integer index of the branch within its group.
            reward: per-step reward, shape ``[*batch]`` or ``[*batch, 1]``.
            mask: boolean, ``True`` on valid steps.
            advantage: written, shape ``[*batch, 1]``.
        """

        group_id: NestedKey = "group_id"
        branch: NestedKey = "branch"
        reward: NestedKey = ("next", "reward")
        mask: NestedKey = "mask"
        advantage: NestedKey = "advantage"

    def __init__(
        self,
        *,
        returns: Returns = "branch",
        baseline: Baseline = "mean",
        scale_rewards: RewardScaling = "group",
        gamma: float = 1.0,
        eps: float = 1e-4,
    ) -> None:
        super().__init__()
        _check_choice("returns", returns, get_args(Returns))
        _check_choice("baseline", baseline, get_args(Baseline))
        _check_choice("scale_rewards", scale_rewards, get_args(RewardScaling))
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma}.")
        if eps < 0:
            raise ValueError(f"eps must be non-negative, got {eps}.")
        self.returns = returns
        self.baseline = baseline
        self.scale_rewards = scale_rewards
        self.gamma = float(gamma)
        self.eps = float(eps)
        self.tensor_keys = self._AcceptedKeys()

    def set_keys(self, **kwargs: NestedKey) -> GroupRelativeAdvantage:
        """Renames the keys read and written, e.g. ``set_keys(reward="r")``.

        Raises:
            ValueError: for a name that is not one of the accepted keys.
        """
        accepted = {f.name for f in fields(self._AcceptedKeys)}
        for name, value in kwargs.items():
            if name not in accepted:
                raise ValueError(
                    f"{name!r} is not an accepted key of {type(self).__name__}; "
                    f"accepted keys are {sorted(accepted)}."
                )
            setattr(self.tensor_keys, name, value)
        return self

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        k = self.tensor_keys
        return [k.group_id, k.branch, k.reward, k.mask]

    @property
    def out_keys(self) -> list[NestedKey]:  # noqa: D102
        return [self.tensor_keys.advantage]

    def _get(self, tensordict: TensorDictBase, name: str) -> torch.Tensor:
        key = getattr(self.tensor_keys, name)
        value = tensordict.get(key, None)
        if value is None:
            raise ValueError(
                f"{type(self).__name__}: the input has no {key!r} entry (the {name!r} key; "
                f"rename it with set_keys({name}=...))."
            )
        return _flatten_batch(value, tensordict.batch_size, key)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes the advantage into ``tensordict`` and returns it."""
        keys = self.tensor_keys
        group_id = self._get(tensordict, "group_id")
        branch = self._get(tensordict, "branch")
        reward = self._get(tensordict, "reward")
        mask = self._get(tensordict, "mask")
        if mask.dtype != torch.bool:
            raise ValueError(f"{keys.mask!r} must be boolean, got dtype {mask.dtype}.")
        valid = mask.nonzero().squeeze(-1)
        if not valid.numel():
            raise ValueError(f"{keys.mask!r} marks no valid step: nothing to compute.")
        gid, reward_v = group_id[valid], reward[valid]
        traj, traj_group, group_values = trajectory_index(
            gid, branch[valid], group_key=keys.group_id, branch_key=keys.branch
        )
        n_traj, n_groups = traj_group.numel(), group_values.numel()
        row_length = tensordict.batch_size[-1] if tensordict.batch_dims >= 2 else None
        check_distinct_trajectories(
            traj,
            valid,
            row_length,
            gid,
            branch[valid],
            group_key=keys.group_id,
            branch_key=keys.branch,
        )

        bad = ~torch.isfinite(reward_v)
        if bad.any():
            ids = torch.unique(gid[bad]).tolist()
            raise ValueError(
                f"{keys.reward!r} is NaN or infinite on valid steps of groups {ids[:10]}."
            )
        branches_per_group = torch.bincount(traj_group, minlength=n_groups)
        lonely = branches_per_group < 2
        if lonely.any():
            ids = group_values[lonely].tolist()
            raise ValueError(
                f"groups {ids[:10]} (key {keys.group_id!r}) have a single branch: a "
                "group-relative advantage needs at least two branches per group."
            )

        # float64: the discounted sums and the group statistics are cheap, and
        # float32 loses the difference between close returns of long branches.
        reward_v = reward_v.to(torch.float64)
        if self.returns == "branch":
            if self.gamma != 1.0:
                pos = positions_in_segments(traj, n_traj)
                reward_v = reward_v * self._discounts(pos)
            unit_values = segment_sum(reward_v, traj, n_traj)
            unit, unit_group = traj, traj_group
        else:
            pos = positions_in_segments(traj, n_traj)
            unit_values = self._reward_to_go(reward_v, traj, pos, n_traj)
            # a per-step group: the branches of one root at the same step index
            code = traj_group[traj] * (int(pos.max()) + 1) + pos
            _, unit_group = torch.unique(code, return_inverse=True)
            unit = torch.arange(unit_values.numel(), device=unit_values.device)
        adv_units = self._normalise(unit_values, unit_group)

        dtype = reward.dtype if reward.dtype.is_floating_point else torch.get_default_dtype()
        advantage = torch.zeros(mask.shape, dtype=dtype, device=mask.device)
        advantage[valid] = adv_units[unit].to(dtype)
        tensordict.set(keys.advantage, advantage.view(*tensordict.batch_size, 1))
        return tensordict

    def _discounts(self, pos: torch.Tensor) -> torch.Tensor:
        if self.gamma == 1.0:
            return torch.ones(pos.shape, dtype=torch.float64, device=pos.device)
        if self.gamma ** int(pos.max()) < _MIN_DISCOUNT:
            raise ValueError(
                f"trajectories of {int(pos.max()) + 1} steps are too long for gamma={self.gamma}: "
                "gamma ** length underflows float64."
            )
        return torch.pow(torch.tensor(self.gamma, dtype=torch.float64), pos.to(torch.float64))

    def _reward_to_go(
        self, reward: torch.Tensor, traj: torch.Tensor, pos: torch.Tensor, n_traj: int
    ) -> torch.Tensor:
        # sum_{j >= t} gamma^(j - t) r_j = (sum_{j >= t} gamma^j r_j) / gamma^t, with the
        # suffix sums taken inside each trajectory from one global cumsum over
        # trajectory-sorted steps: no loop over time.
        disc = self._discounts(pos)
        weighted = reward * disc
        order = torch.argsort(traj, stable=True)
        sorted_w = weighted[order]
        csum = torch.cumsum(sorted_w, 0)
        seg_end = torch.cumsum(torch.bincount(traj, minlength=n_traj), 0) - 1
        suffix = csum[seg_end][traj[order]] - csum + sorted_w
        rtg = torch.empty_like(suffix)
        rtg[order] = suffix
        return rtg / disc

    def _normalise(self, values: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
        n = int(group.max()) + 1
        count, total, mean, std, constant = segment_mean_std(values, group, n)
        if self.baseline == "mean":
            centred = values - mean[group]
        else:
            others = (count[group] - 1).clamp_min(1)
            centred = values - (total[group] - values) / others
        if self.scale_rewards == "group":
            centred = centred / (std[group] + self.eps)
        elif self.scale_rewards == "batch":
            centred = centred / (values.std() + self.eps)
        # exactly zero, not a rounding residue over eps, for groups with no signal
        degenerate = constant | (count < 2)
        return torch.where(degenerate[group], torch.zeros_like(centred), centred)

    def extra_repr(self) -> str:  # noqa: D102
        return (
            f"returns={self.returns!r}, baseline={self.baseline!r}, "
            f"scale_rewards={self.scale_rewards!r}, gamma={self.gamma}, eps={self.eps}"
        )


def _check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}.")


def _flatten_batch(value: torch.Tensor, batch_size: torch.Size, key: NestedKey) -> torch.Tensor:
    # Per-step entries come as [*batch] or [*batch, 1]; anything else is a
    # layout error that a silent reshape would hide.
    n = math.prod(batch_size)
    if value.shape == batch_size or value.shape == (*batch_size, 1):
        return value.reshape(n)
    raise ValueError(
        f"{key!r} has shape {tuple(value.shape)}; expected {tuple(batch_size)} or "
        f"{(*batch_size, 1)} for a tensordict of batch size {tuple(batch_size)}."
    )
