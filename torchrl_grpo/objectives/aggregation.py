"""How a loss term is averaged over the valid steps: the aggregations of :class:`GRPOLoss`.

An aggregation names a normalising *rule*:

- ``"step_mean"``: the mean over all valid steps;
- ``"trajectory_mean"``: the mean over each trajectory's valid steps, then over
  trajectories;
- ``"constant"``: the sum over valid steps divided by ``n_trajectories * max_steps``.

:func:`step_weights` turns a rule into one weight per valid step, and
:func:`aggregate` applies the weights.
"""

from __future__ import annotations

from typing import Literal

import torch

__all__ = [
    "AGGREGATION_RULES",
    "Aggregation",
    "AggregationRule",
    "aggregate",
    "check_aggregation",
    "step_weights",
    "time_trajectories",
]

Aggregation = Literal["dapo", "bnpo", "token_mean", "grpo", "prompt_mean", "dr_grpo"]
"""Loss aggregations: TRL's ``loss_type`` names and TorchRL's ``aggregation`` names."""

AggregationRule = Literal["step_mean", "trajectory_mean", "constant"]
"""The normalising rules the aggregations name (see the module docstring)."""

#: The rule of every aggregation. Several names for one rule: TRL's loss_type and
#: TorchRL's aggregation spell the same normalisers differently; users of either
#: should feel at home.
AGGREGATION_RULES: dict[str, AggregationRule] = {
    "dapo": "step_mean",
    "bnpo": "step_mean",
    "token_mean": "step_mean",
    "grpo": "trajectory_mean",
    "prompt_mean": "trajectory_mean",
    "dr_grpo": "constant",
}


def check_aggregation(aggregation: str) -> None:
    """Raises a ``ValueError`` unless ``aggregation`` is an :data:`Aggregation`.

    Example:
        >>> check_aggregation("dr_grpo")
        >>> check_aggregation("sum")
        Traceback (most recent call last):
        ...
        ValueError: aggregation must be one of ['bnpo', 'dapo', 'dr_grpo', 'grpo', 'prompt_mean', 'token_mean'], got 'sum'.
    """  # noqa: E501 - a doctest's expected output is one line
    if aggregation not in AGGREGATION_RULES:
        raise ValueError(
            f"aggregation must be one of {sorted(AGGREGATION_RULES)}, got {aggregation!r}."
        )


def time_trajectories(
    n_steps: int, horizon: int, valid_idx: torch.Tensor | None, device: torch.device
) -> tuple[torch.Tensor, int]:
    """The trajectory of every valid step of a batch whose last dimension is time.

    Args:
        n_steps: steps in the batch (valid or not).
        horizon: the batch's last dimension.
        valid_idx: flat indices of the valid steps (``None``: all are valid).
        device: device of the result.

    Returns:
        ``(traj, n_rows)``: the row (trajectory) of each valid step, and the number of
        rows of the batch.

    Example:
        >>> traj, n_rows = time_trajectories(6, 3, torch.tensor([0, 1, 3]), torch.device("cpu"))
        >>> traj.tolist(), n_rows
        ([0, 0, 1], 2)
    """
    flat = torch.arange(n_steps, device=device)
    traj = (flat if valid_idx is None else valid_idx) // horizon
    return traj, n_steps // horizon


def step_weights(
    rule: AggregationRule,
    traj: torch.Tensor,
    n_rows: int,
    n_valid: int,
    max_steps: int | None,
    device: torch.device,
) -> torch.Tensor | None:
    """Per-valid-step weights of ``rule``; ``None`` for a plain mean (``"step_mean"``).

    A row without any valid step is padding, not a trajectory.

    Args:
        rule: the aggregation's rule (:data:`AGGREGATION_RULES`).
        traj: ``[n_valid]`` the trajectory (row) of each valid step.
        n_rows: the number of rows ``traj`` indexes.
        n_valid: the number of valid steps.
        max_steps: the ``"constant"`` rule's ``L`` (``None``: the longest trajectory).
        device: device of the ``"constant"`` weights.

    Returns:
        ``[n_valid]`` weights in torch's default dtype, or ``None``.

    Example:
        >>> traj = torch.tensor([0, 0, 0, 2])  # row 1 is padding
        >>> step_weights("trajectory_mean", traj, 3, 4, None, traj.device).tolist()
        [0.1666..., 0.1666..., 0.1666..., 0.5]
        >>> step_weights("constant", traj, 3, 4, 4, traj.device).tolist()
        [0.125, 0.125, 0.125, 0.125]
    """
    if rule == "step_mean":
        return None
    counts = torch.bincount(traj, minlength=n_rows)
    n_traj = int((counts > 0).sum())
    if rule == "trajectory_mean":
        weights = 1.0 / (counts[traj] * n_traj)
    else:
        max_steps = max_steps or int(counts.max())
        weights = torch.full((n_valid,), 1.0 / (n_traj * max_steps), device=device)
    return weights.to(torch.get_default_dtype())


def aggregate(values: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """The weighted sum of per-step ``values`` (their mean when ``weights`` is ``None``).

    Example:
        >>> values = torch.tensor([1.0, 2.0, 3.0, 6.0])
        >>> aggregate(values, None).item(), aggregate(values, torch.full((4,), 0.5)).item()
        (3.0, 6.0)
    """
    if weights is None:
        return values.mean()
    return (values * weights.to(values.dtype)).sum()
