"""Critic-free objectives: group-relative advantages, GRPOLoss, KL estimators, reference sync.

Also the distillation of enumerated groups' action comparisons (``GroupDistillLoss``,
``AdvantageRegressionLoss``), the loss of a crash head (``CrashHeadLoss``) and what it
tells the horizon bootstrap and its own labels (``TailSurvival``, ``crash_label``), and
the distillation of trained teachers into one policy (``TeacherDistillLoss``, and
``TeacherCrashLoss`` for their crash heads).
"""

from torchrl_grpo.objectives.advantage import GroupRelativeAdvantage
from torchrl_grpo.objectives.bootstrap import BootstrapMode, HorizonBootstrap
from torchrl_grpo.objectives.crash_head import CrashHeadLoss
from torchrl_grpo.objectives.distill import GroupDistillLoss, group_softmax_target, group_spread
from torchrl_grpo.objectives.grpo import Aggregation, GRPOLoss
from torchrl_grpo.objectives.kl import KLEstimator, analytic_kl, kl_estimate
from torchrl_grpo.objectives.reference import ReferenceSync
from torchrl_grpo.objectives.regression import AdvantageRegressionLoss
from torchrl_grpo.objectives.survival import CrashLabel, TailSurvival, crash_label
from torchrl_grpo.objectives.teacher import TeacherCrashLoss, TeacherDistillLoss

__all__ = [
    "AdvantageRegressionLoss",
    "Aggregation",
    "BootstrapMode",
    "CrashHeadLoss",
    "CrashLabel",
    "GRPOLoss",
    "GroupDistillLoss",
    "GroupRelativeAdvantage",
    "HorizonBootstrap",
    "KLEstimator",
    "ReferenceSync",
    "TailSurvival",
    "TeacherCrashLoss",
    "TeacherDistillLoss",
    "analytic_kl",
    "crash_label",
    "group_softmax_target",
    "group_spread",
    "kl_estimate",
]
