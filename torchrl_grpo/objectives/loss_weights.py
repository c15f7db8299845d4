"""The per-step weights of a :class:`~torchrl_grpo.objectives.GRPOLoss` batch.

An aggregation's normaliser needs the trajectories of the batch: the rows of its last
dimension when it has two or more, the ``(group_id, branch)`` pairs of a flat one.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

from torchrl_grpo.objectives._segments import trajectory_index
from torchrl_grpo.objectives.aggregation import (
    AGGREGATION_RULES,
    step_weights,
    time_trajectories,
)
from torchrl_grpo.objectives.loss_checks import per_step, require

__all__ = ["batch_step_weights"]


def batch_step_weights(
    tensordict: TensorDictBase,
    mask: torch.Tensor,
    valid_idx: torch.Tensor | None,
    aggregation: str,
    max_steps: int | None,
    keys: Any,
) -> torch.Tensor | None:
    """Weights of the valid steps of ``tensordict`` under ``aggregation``; ``None``: a mean.

    Args:
        tensordict: the loss input, batch ``[R, G, T]``, ``[N, T]`` or flat ``[B]``.
        mask: the flat valid-step mask, ``[numel(batch)]``.
        valid_idx: the flat indices of the valid steps (``None``: all are valid).
        aggregation: one of :data:`~torchrl_grpo.objectives.aggregation.AGGREGATION_RULES`.
        max_steps: Dr. GRPO's constant (``None``: the time dimension or the longest
            trajectory).
        keys: the loss's accepted keys (``group_id`` and ``branch`` of a flat batch).

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.objectives import GRPOLoss
        >>> td = TensorDict(batch_size=[2, 3])
        >>> mask = torch.tensor([True, True, True, True, False, False])
        >>> keys = GRPOLoss.default_keys()
        >>> batch_step_weights(td, mask, mask.nonzero().squeeze(-1), "grpo", None, keys)
        tensor([0.1667, 0.1667, 0.1667, 0.5000])
    """
    rule = AGGREGATION_RULES[aggregation]
    if rule == "step_mean":
        return None
    batch_size = tensordict.batch_size
    n_valid = mask.numel() if valid_idx is None else valid_idx.numel()
    if len(batch_size) >= 2:
        horizon = batch_size[-1]
        traj, n_rows = time_trajectories(mask.numel(), horizon, valid_idx, mask.device)
    else:
        group_id = per_step(
            require(tensordict, keys.group_id, "group_id"), batch_size, keys.group_id
        )
        branch = per_step(require(tensordict, keys.branch, "branch"), batch_size, keys.branch)
        if valid_idx is not None:
            group_id, branch = group_id[valid_idx], branch[valid_idx]
        traj, traj_group, _ = trajectory_index(
            group_id, branch, group_key=keys.group_id, branch_key=keys.branch
        )
        n_rows = traj_group.numel()
        horizon = None
    return step_weights(rule, traj, n_rows, n_valid, max_steps or horizon, mask.device)
