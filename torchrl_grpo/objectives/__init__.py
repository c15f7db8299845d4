"""Critic-free objectives: group-relative advantages, GRPOLoss, KL estimators, reference sync."""

from torchrl_grpo.objectives.advantage import GroupRelativeAdvantage
from torchrl_grpo.objectives.bootstrap import BootstrapMode, HorizonBootstrap
from torchrl_grpo.objectives.grpo import Aggregation, GRPOLoss
from torchrl_grpo.objectives.kl import KLEstimator, analytic_kl, kl_estimate
from torchrl_grpo.objectives.reference import ReferenceSync

__all__ = [
    "Aggregation",
    "BootstrapMode",
    "GRPOLoss",
    "GroupRelativeAdvantage",
    "HorizonBootstrap",
    "KLEstimator",
    "ReferenceSync",
    "analytic_kl",
    "kl_estimate",
]
