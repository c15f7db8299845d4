"""The value checks of :class:`~torchrl_grpo.objectives.GRPOLoss`: arguments and inputs.

The loss input is a tensordict of batch size ``[*batch]`` (``[R, G, T]``, ``[N, T]``
or flat ``[B]``) with one value per step: these helpers read an entry with an error
that names its key, flatten it to ``[numel(batch)]`` and sum a distribution's event
dimensions. :func:`check_loss_args` checks the loss's arguments and
:func:`check_finite` its per-step values; :func:`check_crash_head_args` those of the
losses of a crash head.
"""

from __future__ import annotations

import math

import torch
from tensordict import NestedKey, TensorDictBase

from torchrl_grpo.objectives.aggregation import check_aggregation

__all__ = [
    "behaviour_log_prob",
    "check_crash_head_args",
    "check_finite",
    "check_loss_args",
    "per_step",
    "require",
    "sum_event",
]


def require(tensordict: TensorDictBase, key: NestedKey, name: str, hint: str = "") -> torch.Tensor:
    """The ``key`` entry of ``tensordict``; the error names the key and how to rename it.

    Args:
        tensordict: the loss input.
        key: the entry's key.
        name: the field of the loss's ``_AcceptedKeys`` that holds ``key``.
        hint: appended to the error message.

    Example:
        >>> from tensordict import TensorDict
        >>> require(TensorDict(mask=torch.ones(2, dtype=torch.bool)), "mask", "mask").tolist()
        [True, True]
        >>> require(TensorDict(), "adv", "advantage")
        Traceback (most recent call last):
        ...
        ValueError: the input has no 'adv' entry (the 'advantage' key; rename it with set_keys(advantage=...)).
    """  # noqa: E501 - a doctest's expected output is one line
    value = tensordict.get(key, None)
    if value is None:
        raise ValueError(
            f"the input has no {key!r} entry (the {name!r} key; rename it with "
            f"set_keys({name}=...)).{hint}"
        )
    return value


def per_step(value: torch.Tensor, batch_size: torch.Size, key: object) -> torch.Tensor:
    """``[*batch]`` or ``[*batch, 1]`` as ``[numel(batch)]``; any other shape is an error.

    Example:
        >>> per_step(torch.zeros(2, 3, 1), torch.Size([2, 3]), "advantage").shape
        torch.Size([6])
    """
    if value.shape == batch_size or value.shape == (*batch_size, 1):
        return value.reshape(-1)
    raise ValueError(
        f"{key!r} has shape {tuple(value.shape)}; expected {tuple(batch_size)} or "
        f"{(*batch_size, 1)}."
    )


def sum_event(value: torch.Tensor, n_batch: int) -> torch.Tensor:
    """Sums the dimensions after the ``n_batch`` batch dimensions (the event's).

    ``Normal`` (not ``Independent``) returns per-dimension log-probs and entropies: the
    joint over the action dimensions is their sum.

    Example:
        >>> sum_event(torch.ones(4, 3), n_batch=1).tolist()
        [3.0, 3.0, 3.0, 3.0]
    """
    if value.ndim > n_batch:
        return value.sum(tuple(range(n_batch, value.ndim)))
    return value


def behaviour_log_prob(steps: TensorDictBase, key: NestedKey) -> torch.Tensor:
    """The stored behaviour log-prob of each step, ``[numel(batch)]``, detached.

    Example:
        >>> from tensordict import TensorDict
        >>> steps = TensorDict(action_log_prob=torch.zeros(3), batch_size=[3])
        >>> behaviour_log_prob(steps, "action_log_prob").shape
        torch.Size([3])
    """
    value = steps.get(key, None)
    if value is None:
        others = [k for k in ("sample_log_prob", "action_log_prob") if k in steps.keys()]
        hint = f" The input has {others}: call set_keys(sample_log_prob=...)." if others else ""
        raise ValueError(f"the input has no {key!r} entry (behaviour log-prob).{hint}")
    if value.requires_grad:
        raise ValueError(f"{key!r} requires grad: store the behaviour log-prob detached.")
    return per_step(sum_event(value, len(steps.batch_size)), steps.batch_size, key)


def check_finite(values: dict[str, torch.Tensor | None]) -> None:
    """Raise a ``ValueError`` naming the first of ``values`` that holds a NaN or an inf.

    One device synchronisation for all of them; ``None`` entries are skipped. A
    non-finite advantage or log-prob on a valid step makes the loss and every
    gradient NaN, which an optimiser step would write into the weights.

    Args:
        values: per-step tensors of the valid steps, by the name the error gives.

    Example:
        >>> check_finite({"'advantage'": torch.tensor([0.5, float("nan")])})
        Traceback (most recent call last):
        ...
        ValueError: 'advantage' is NaN or infinite on 1 of 2 valid steps: the loss and its gradients would be NaN. (GRPOLoss(check_values=False) skips this check.)
    """  # noqa: E501 - a doctest's expected output is one line
    present = {name: v for name, v in values.items() if v is not None}
    if not present:
        return
    # A NaN or inf anywhere makes the sum non-finite: one reduction per tensor on the
    # common path; finite values whose sum overflows fall through to the exact check.
    if bool(torch.isfinite(torch.stack([v.sum() for v in present.values()]).sum())):
        return
    for name, value in present.items():
        bad = int((~torch.isfinite(value)).sum())
        if bad:
            raise ValueError(
                f"{name} is NaN or infinite on {bad} of {value.numel()} valid steps: the loss "
                "and its gradients would be NaN. (GRPOLoss(check_values=False) skips this check.)"
            )


def check_crash_head_args(head: torch.nn.Module, coeff: float, hint: str) -> None:
    """Checks the arguments of a crash head's loss: a head with crash logits, its weight.

    Args:
        head: must have ``crash_logits(observation)``.
        coeff: the loss's weight, a finite number ``> 0``.
        hint: what the ``TypeError`` tells the user to do when ``head`` has none.

    Example:
        >>> check_crash_head_args(torch.nn.Linear(2, 2), 1.0, "wrap it in a CrashHead")
        Traceback (most recent call last):
        ...
        TypeError: Linear has no crash_logits(observation): wrap it in a CrashHead
    """
    if not callable(getattr(head, "crash_logits", None)):
        raise TypeError(f"{type(head).__name__} has no crash_logits(observation): {hint}")
    if not (coeff > 0 and coeff < math.inf):
        raise ValueError(f"coeff must be a finite number > 0, got {coeff}")


def check_loss_args(
    *,
    aggregation: str,
    kl_estimator: str,
    clip_epsilon: float | tuple[float, float],
    dual_clip: float | None,
    max_steps: int | None,
    samples_mc_entropy: int,
    kl_to_ref_coeff: float | None = None,
    entropy_coeff: float = 0.0,
) -> tuple[float, float]:
    """Checks :class:`~torchrl_grpo.objectives.GRPOLoss`'s arguments (see it for each).

    Returns:
        ``(eps_low, eps_high)``: the clip bounds of a symmetric ``clip_epsilon`` or of a
        ``(low, high)`` pair.

    Example:
        >>> check_loss_args(aggregation="dapo", kl_estimator="k3", clip_epsilon=(0.2, 0.28),
        ...                 dual_clip=None, max_steps=None, samples_mc_entropy=1)
        (0.2, 0.28)
    """
    check_aggregation(aggregation)
    if kl_estimator not in ("k1", "k2", "k3", "analytic"):
        raise ValueError(
            f"kl_estimator must be 'k1', 'k2', 'k3' or 'analytic', got {kl_estimator!r}."
        )
    eps_low, eps_high = _clip_bounds(clip_epsilon)
    if dual_clip is not None and not (1.0 < dual_clip < math.inf):
        raise ValueError(f"dual_clip must be > 1 and finite, got {dual_clip}.")
    if kl_to_ref_coeff is not None and not (0.0 <= kl_to_ref_coeff < math.inf):
        raise ValueError(
            f"kl_to_ref_coeff must be >= 0 and finite (or None), got {kl_to_ref_coeff}."
        )
    if not 0.0 <= entropy_coeff < math.inf:
        raise ValueError(f"entropy_coeff must be >= 0 and finite, got {entropy_coeff}.")
    if max_steps is not None and max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}.")
    if samples_mc_entropy < 1:
        raise ValueError(f"samples_mc_entropy must be >= 1, got {samples_mc_entropy}.")
    return eps_low, eps_high


def _clip_bounds(clip_epsilon: float | tuple[float, float]) -> tuple[float, float]:
    if isinstance(clip_epsilon, (tuple, list)):
        if len(clip_epsilon) != 2:
            raise ValueError(f"clip_epsilon must be a float or (low, high), got {clip_epsilon}.")
        low, high = float(clip_epsilon[0]), float(clip_epsilon[1])
    else:
        low = high = float(clip_epsilon)
    if not (0.0 <= low < 1.0 and high >= 0.0 and math.isfinite(high)):
        raise ValueError(f"clip_epsilon needs 0 <= low < 1 and 0 <= high, got ({low}, {high}).")
    return low, high
