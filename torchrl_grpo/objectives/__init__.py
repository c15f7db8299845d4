"""Critic-free objectives: group-relative advantages, GRPOLoss, KL estimators, reference sync.

Also the distillation of enumerated groups' action comparisons (``GroupDistillLoss``).
"""

from torchrl_grpo.objectives.advantage import GroupRelativeAdvantage
from torchrl_grpo.objectives.bootstrap import BootstrapMode, HorizonBootstrap
from torchrl_grpo.objectives.distill import GroupDistillLoss, group_softmax_target
from torchrl_grpo.objectives.grpo import Aggregation, GRPOLoss
from torchrl_grpo.objectives.kl import KLEstimator, analytic_kl, kl_estimate
from torchrl_grpo.objectives.reference import ReferenceSync

__all__ = [
    "Aggregation",
    "BootstrapMode",
    "GRPOLoss",
    "GroupDistillLoss",
    "GroupRelativeAdvantage",
    "HorizonBootstrap",
    "KLEstimator",
    "ReferenceSync",
    "analytic_kl",
    "group_softmax_target",
    "kl_estimate",
]
