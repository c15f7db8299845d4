"""Builder of the ``optim`` group: Adam over a loss's trainable parameters, its schedule."""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from torch import nn

__all__ = ["anneal_lr", "make_optimizer"]


def make_optimizer(optim_cfg: DictConfig, loss: nn.Module) -> torch.optim.Optimizer:
    """Adam over the loss's trainable parameters (policy, and critic for PPO).

    The reference policy of a GRPO loss is a frozen copy (no gradient), so it is left out.

    Example:
        >>> from omegaconf import OmegaConf
        >>> opt = make_optimizer(OmegaConf.create({"lr": 1e-3}), torch.nn.Linear(2, 2))
        >>> type(opt).__name__
        'Adam'
    """
    params = [p for p in loss.parameters() if p.requires_grad]
    return torch.optim.Adam(
        params,
        lr=float(optim_cfg.lr),
        weight_decay=float(optim_cfg.get("weight_decay", 0.0)),
        eps=float(optim_cfg.get("eps", 1e-8)),
    )


def anneal_lr(
    optimizer: torch.optim.Optimizer, optim_cfg: DictConfig, frames: int, total: int
) -> None:
    """With ``optim.anneal_lr``, set the learning rate to ``lr * (1 - frames / total)``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"lr": 1e-3, "weight_decay": 0.0, "eps": 1e-8,
        ...                         "anneal_lr": True})
        >>> opt = make_optimizer(cfg, torch.nn.Linear(2, 2))
        >>> anneal_lr(opt, cfg, frames=750, total=1000)
        >>> opt.param_groups[0]["lr"]
        0.00025
    """
    if not optim_cfg.anneal_lr:
        return
    frac = max(0.0, 1.0 - frames / total)
    for group in optimizer.param_groups:
        group["lr"] = float(optim_cfg.lr) * frac
