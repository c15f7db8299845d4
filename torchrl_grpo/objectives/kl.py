"""Per-sample estimators of KL(pi_theta || pi_ref) and the analytic divergence.

The sample-based estimators follow J. Schulman, "Approximating KL Divergence"
(2020), with ``log r = log pi_ref(a) - log pi_theta(a)`` for an action ``a`` drawn
from pi_theta (in practice from the behaviour policy, close to it):

- ``k1 = -log r``: unbiased, can be negative, high variance;
- ``k2 = (log r) ** 2 / 2``: biased (second order), always >= 0, low variance;
  verl's ``kl_loss_type="mse"``;
- ``k3 = (r - 1) - log r``: unbiased, always >= 0, low variance; DeepSeekMath's
  GRPO penalty and verl's ``low_var_kl``.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import distributions as d

__all__ = ["KLEstimator", "analytic_kl", "kl_estimate"]

KLEstimator = Literal["k1", "k2", "k3", "analytic"]
"""Names accepted by :class:`~torchrl_grpo.objectives.GRPOLoss`'s ``kl_estimator``."""


def kl_estimate(
    log_prob: torch.Tensor, ref_log_prob: torch.Tensor, estimator: Literal["k1", "k2", "k3"]
) -> torch.Tensor:
    """Per-sample estimate of KL(pi_theta || pi_ref) from two log-probabilities.

    Args:
        log_prob: log pi_theta(a), differentiable.
        ref_log_prob: log pi_ref(a) of the same actions, without gradient.
        estimator: ``"k1"``, ``"k2"`` or ``"k3"``.

    Returns:
        A tensor shaped like ``log_prob``; its mean over actions sampled from
        pi_theta is the estimate.

    Example:
        >>> import torch
        >>> from torchrl_grpo.objectives import kl_estimate
        >>> lp, ref = torch.tensor([-1.0, -2.0]), torch.tensor([-1.5, -1.0])
        >>> kl_estimate(lp, ref, "k1")
        tensor([ 0.5000, -1.0000])
        >>> kl_estimate(lp, ref, "k3")
        tensor([0.1065, 0.7183])
    """
    log_ratio = ref_log_prob - log_prob
    if estimator == "k1":
        return -log_ratio
    if estimator == "k2":
        return 0.5 * log_ratio.square()
    if estimator == "k3":
        # expm1 keeps precision when the policies are close (log r ~ 0)
        return torch.expm1(log_ratio) - log_ratio
    raise ValueError(f"estimator must be one of 'k1', 'k2', 'k3', got {estimator!r}.")


def analytic_kl(dist: d.Distribution, ref_dist: d.Distribution) -> torch.Tensor:
    """Closed-form KL(dist || ref_dist) per batch element.

    Covers every pair registered with :func:`torch.distributions.kl_divergence`,
    including Categorical, Normal, TorchRL's IndependentNormal and TanhNormal (whose
    KL is that of the underlying normals, the tanh being a shared bijection).

    Raises:
        ValueError: when the pair has no closed form (use ``"k3"`` instead).

    Example:
        >>> import torch
        >>> from torch.distributions import Categorical
        >>> from torchrl_grpo.objectives.kl import analytic_kl
        >>> p = Categorical(probs=torch.tensor([0.5, 0.5]))
        >>> q = Categorical(probs=torch.tensor([0.25, 0.75]))
        >>> analytic_kl(p, q)
        tensor(0.1438)
    """
    try:
        return d.kl_divergence(dist, ref_dist)
    except NotImplementedError as err:
        raise ValueError(
            f"no analytic KL between {type(dist).__name__} and {type(ref_dist).__name__}; "
            "use kl_estimator='k3' (or 'k1', 'k2')."
        ) from err
