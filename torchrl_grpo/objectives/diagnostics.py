"""The diagnostics :class:`~torchrl_grpo.objectives.GRPOLoss` reports beside its terms."""

from __future__ import annotations

import torch

__all__ = ["RATIO_DIAGNOSTICS", "ratio_diagnostics"]

#: The keys :func:`ratio_diagnostics` writes, in order.
RATIO_DIAGNOSTICS: tuple[str, ...] = (
    "clip_fraction",
    "kl_approx",
    "ESS",
    "min_ratio",
    "mean_ratio",
    "max_ratio",
    "advantage_mean",
    "advantage_std",
)


@torch.no_grad()
def ratio_diagnostics(
    log_weight: torch.Tensor, log_weight_clip: torch.Tensor, advantage: torch.Tensor
) -> dict[str, torch.Tensor]:
    """Statistics of the importance ratios and advantages of the valid steps.

    ``clip_fraction`` (share of clipped ratios), ``kl_approx`` (mean ``log pi_old - log
    pi_theta``), ``ESS`` (normalised effective sample size of the ratios, in (0, 1]),
    ``min_ratio``, ``mean_ratio``, ``max_ratio``, ``advantage_mean`` and
    ``advantage_std``.

    Args:
        log_weight: ``[n_valid]`` ``log pi_theta - log pi_old`` per valid step.
        log_weight_clip: ``log_weight`` clipped to the trust region.
        advantage: ``[n_valid]`` the advantages.

    Example:
        >>> log_weight = torch.tensor([0.0, 0.0, 0.5, -0.3])
        >>> out = ratio_diagnostics(log_weight, log_weight.clamp(-0.2, 0.2), torch.ones(4))
        >>> [round(out[k].item(), 3) for k in ("clip_fraction", "kl_approx", "max_ratio")]
        [0.5, -0.05, 1.649]
    """
    out = {}
    n = log_weight.numel()
    lw = log_weight.detach()
    ratio = lw.exp()
    out["clip_fraction"] = (log_weight_clip != log_weight).sum() / n
    out["kl_approx"] = -lw.mean()
    out["ESS"] = (2 * lw.logsumexp(0) - (2 * lw).logsumexp(0)).exp() / n
    out["min_ratio"], out["max_ratio"] = torch.aminmax(ratio)
    out["mean_ratio"] = ratio.mean()
    out["advantage_mean"] = advantage.mean()
    out["advantage_std"] = advantage.std(correction=0)
    return out
