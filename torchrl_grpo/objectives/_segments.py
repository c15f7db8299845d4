"""Vectorised segment arithmetic shared by the advantage module and the loss.

A *segment* is a set of entries of a flat tensor sharing an integer label (a
trajectory, a group). Everything here is scatter / index_add based, so the cost
is linear in the number of entries and independent of how many segments exist.
"""

from __future__ import annotations

import torch

__all__ = [
    "check_distinct_trajectories",
    "positions_in_segments",
    "segment_mean_std",
    "segment_sum",
    "trajectory_index",
]


def _check_integer(name: str, value: torch.Tensor) -> None:
    if value.dtype.is_floating_point or value.dtype.is_complex or value.dtype == torch.bool:
        raise ValueError(f"{name!r} must hold integers, got dtype {value.dtype}.")


def trajectory_index(
    group_id: torch.Tensor, branch: torch.Tensor, *, group_key: object, branch_key: object
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Label every step with its trajectory, identified by the pair (group id, branch).

    Args:
        group_id: flat integer tensor, the root (group) of each step.
        branch: flat integer tensor, the branch index of each step within its group.
        group_key: key name of ``group_id``, used in error messages.
        branch_key: key name of ``branch``, used in error messages.

    Returns:
        ``(traj, traj_group, group_values)``: ``traj[i]`` in ``[0, n_traj)`` is the
        trajectory of step ``i``; ``traj_group[k]`` in ``[0, n_groups)`` is the group
        of trajectory ``k``; ``group_values[j]`` is the original id of group ``j``.
    """
    _check_integer(str(group_key), group_id)
    _check_integer(str(branch_key), branch)
    if branch.numel() and int(branch.min()) < 0:
        raise ValueError(f"{branch_key!r} must be non-negative, got min {int(branch.min())}.")
    group_values, group_idx = torch.unique(group_id, return_inverse=True)
    n_branch = int(branch.max()) + 1 if branch.numel() else 1
    # One int64 code per (group, branch) pair: a 1-D unique is much cheaper than
    # unique(dim=0) on stacked pairs.
    code = group_idx * n_branch + branch.to(torch.int64)
    codes, traj = torch.unique(code, return_inverse=True)
    traj_group = torch.div(codes, n_branch, rounding_mode="floor")
    return traj, traj_group, group_values


def check_distinct_trajectories(
    traj: torch.Tensor,
    flat_index: torch.Tensor,
    row_length: int | None,
    group_id: torch.Tensor,
    branch: torch.Tensor,
    *,
    group_key: object,
    branch_key: object,
) -> None:
    """Refuse a (group id, branch) pair held by two trajectories of one batch.

    A trajectory's steps are one run in the row-major flattening of the batch (one
    row of a ``[..., T]`` batch): a pair whose steps form two runs, or lie in two
    rows, belongs to two trajectories that would be merged into one.

    Args:
        traj: the trajectory label of each step (from :func:`trajectory_index`).
        flat_index: each step's position in the flattened batch, increasing.
        row_length: ``T`` of a batch of two or more dims (a row is a trajectory);
            ``None`` for a flat batch.
        group_id: each step's group id.
        branch: each step's branch.
        group_key: key name of ``group_id``, used in the error.
        branch_key: key name of ``branch``, used in the error.

    Raises:
        ValueError: naming the first shared pair and ``first_group_id``.

    Example:
        >>> ids, branch = torch.tensor([0, 0, 1, 0]), torch.tensor([0, 0, 0, 0])
        >>> traj, _, _ = trajectory_index(ids, branch, group_key="g", branch_key="b")
        >>> try:
        ...     check_distinct_trajectories(
        ...         traj, torch.arange(4), None, ids, branch, group_key="g", branch_key="b")
        ... except ValueError as err:
        ...     print(str(err)[:48])
        the (g, b) pair (0, 0) is held by 2 trajectories
    """
    if traj.numel() < 2:
        return
    starts = torch.ones_like(traj, dtype=torch.bool)
    starts[1:] = traj[1:] != traj[:-1]
    if row_length is not None:
        rows = torch.div(flat_index, row_length, rounding_mode="floor")
        starts[1:] |= rows[1:] != rows[:-1]
    runs = torch.bincount(traj[starts], minlength=int(traj.max()) + 1)
    shared = runs > 1
    if not bool(shared.any()):
        return
    first = int(torch.nonzero(shared[traj])[0, 0])
    pair = (int(group_id[first]), int(branch[first]))
    raise ValueError(
        f"the ({group_key}, {branch_key}) pair {pair} is held by {int(runs[traj[first]])} "
        "trajectories of the batch, but each root needs its own group id. Batches of "
        "branch_rollout number their roots from first_group_id (0 by default): give each "
        "batch its own range, e.g. first_group_id=<a running count of roots>, before "
        "concatenating them."
    )


def segment_sum(values: torch.Tensor, index: torch.Tensor, n_segments: int) -> torch.Tensor:
    """Sums ``values`` per segment label ``index`` (a flat ``index_add``)."""
    out = values.new_zeros(n_segments)
    return out.index_add_(0, index, values)


def positions_in_segments(index: torch.Tensor, n_segments: int) -> torch.Tensor:
    """Rank of each entry within its segment, counting in flat order (0, 1, 2, ...)."""
    order = torch.argsort(index, stable=True)
    counts = torch.bincount(index, minlength=n_segments)
    starts = torch.cumsum(counts, 0) - counts
    sorted_pos = torch.arange(index.numel(), device=index.device) - starts[index[order]]
    pos = torch.empty_like(sorted_pos)
    pos[order] = sorted_pos
    return pos


def segment_mean_std(
    values: torch.Tensor, index: torch.Tensor, n_segments: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-segment count, sum, mean, unbiased std and an "all members equal" flag.

    Two passes (mean, then squared deviations) rather than a sum of squares,
    which loses precision when returns are large and close together.

    Returns:
        ``(count, total, mean, std, constant)``, each of length ``n_segments``.
        ``std`` is 0 for segments of fewer than two members.
    """
    count = torch.bincount(index, minlength=n_segments).to(values.dtype)
    total = segment_sum(values, index, n_segments)
    mean = total / count.clamp_min(1)
    sq_dev = segment_sum((values - mean[index]).square(), index, n_segments)
    std = (sq_dev / (count - 1).clamp_min(1)).sqrt()
    vmin = values.new_full((n_segments,), float("inf")).scatter_reduce_(
        0, index, values, reduce="amin"
    )
    vmax = values.new_full((n_segments,), float("-inf")).scatter_reduce_(
        0, index, values, reduce="amax"
    )
    return count, total, mean, std, vmin == vmax
