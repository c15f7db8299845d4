"""Per-root targets of an enumerated group: each row's regret and its share of the best set.

A group whose branches each take a different first action from the same root and then
follow a fixed policy scores every action of that root. Its rows (the branches' first
steps) carry the advantages ``A(s, a)`` and the root's ``group_id``; rows of many groups
come in any order. :func:`group_reduce` gives each row a reduction over its own group,
from which the targets of :class:`~torchrl_grpo.objectives.GroupRegretLoss` follow.
"""

from __future__ import annotations

from typing import Literal

import torch

__all__ = ["group_best_set", "group_reduce", "group_regret"]


def group_reduce(
    values: torch.Tensor, group_id: torch.Tensor, reduce: Literal["sum", "amax", "amin"]
) -> torch.Tensor:
    """Each row's reduction over the rows of its group: their sum, largest or smallest value.

    Args:
        values: one value per row, ``[N]`` or ``[N, 1]``.
        group_id: the integer id of each row's root, ``[N]``, in any order.
        reduce: ``"sum"``, ``"amax"`` or ``"amin"``.

    Returns:
        The reductions, shaped like ``values`` (equal within a group).

    Raises:
        ValueError: shapes that disagree, or an unknown ``reduce``.

    Example:
        >>> import torch
        >>> adv = torch.tensor([0.0, 1.0, -3.0, 2.0, 2.0])
        >>> group_reduce(adv, torch.tensor([0, 0, 0, 1, 1]), "amax")
        tensor([1., 1., 1., 2., 2.])
    """
    starts = {"sum": 0.0, "amax": -float("inf"), "amin": float("inf")}
    if reduce not in starts:
        raise ValueError(f"reduce must be one of {sorted(starts)}, got {reduce!r}")
    flat = values.reshape(-1)
    gid = group_id.reshape(-1).long()
    if flat.shape != gid.shape:
        raise ValueError(
            f"one value per row: {flat.numel()} values (advantages) for {gid.numel()} group ids"
        )
    _, inverse = torch.unique(gid, return_inverse=True)
    n_groups = int(inverse.max()) + 1 if inverse.numel() else 0
    total = flat.new_full((n_groups,), starts[reduce]).scatter_reduce(
        0, inverse, flat, reduce=reduce
    )
    return total[inverse].reshape(values.shape)


def group_regret(advantage: torch.Tensor, group_id: torch.Tensor) -> torch.Tensor:
    """Each row's regret: its group's best advantage minus its own (``>= 0``).

    Args:
        advantage: one advantage per row, ``[N]`` or ``[N, 1]``.
        group_id: the integer id of each row's root, ``[N]``.

    Returns:
        The regrets, shaped like ``advantage`` (0 for a group's best rows).

    Raises:
        ValueError: shapes that disagree.

    Example:
        >>> import torch
        >>> adv = torch.tensor([0.0, 1.0, -3.0, 2.0, 2.0])
        >>> group_regret(adv, torch.tensor([0, 0, 0, 1, 1]))
        tensor([1., 0., 4., 0., 0.])
    """
    return group_reduce(advantage, group_id, "amax") - advantage


def group_best_set(advantage: torch.Tensor, group_id: torch.Tensor) -> torch.Tensor:
    """Each row's weight in its group's hard target: ``1 / |best set|`` for a best row, else 0.

    Within every group the weights sum to 1: the rows whose advantage equals the
    group's best share it.

    Args:
        advantage: one advantage per row, ``[N]`` or ``[N, 1]``.
        group_id: the integer id of each row's root, ``[N]``.

    Returns:
        The weights, shaped like ``advantage``.

    Raises:
        ValueError: shapes that disagree.

    Example:
        >>> import torch
        >>> adv = torch.tensor([0.0, 1.0, 1.0, -2.0, 2.0])
        >>> group_best_set(adv, torch.tensor([0, 0, 0, 1, 1]))
        tensor([0.0000, 0.5000, 0.5000, 0.0000, 1.0000])
    """
    best = (group_regret(advantage, group_id) == 0).to(advantage.dtype)
    return best / group_reduce(best, group_id, "sum")
