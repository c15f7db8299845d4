"""Critic-free objectives: group-relative advantages, GRPOLoss, KL estimators, reference sync.

Also the regression of enumerated groups' action comparisons
(``AdvantageRegressionLoss``), the loss of a crash head (``CrashHeadLoss``), and the
distillation of trained teachers into one policy (``TeacherDistillLoss``, and
``TeacherCrashLoss`` for their crash heads). What the losses share (the crash labels and
tail survival of ``survival.py``, the ``Literal`` choices) is imported from its module.
"""

from torchrl_grpo.objectives.advantage import GroupRelativeAdvantage
from torchrl_grpo.objectives.bootstrap import HorizonBootstrap
from torchrl_grpo.objectives.crash_head_loss import CrashHeadLoss
from torchrl_grpo.objectives.grpo_loss import GRPOLoss
from torchrl_grpo.objectives.kl import kl_estimate
from torchrl_grpo.objectives.reference import ReferenceSync
from torchrl_grpo.objectives.regression import AdvantageRegressionLoss
from torchrl_grpo.objectives.teacher_losses import TeacherCrashLoss, TeacherDistillLoss

__all__ = [
    "AdvantageRegressionLoss",
    "CrashHeadLoss",
    "GRPOLoss",
    "GroupRelativeAdvantage",
    "HorizonBootstrap",
    "ReferenceSync",
    "TeacherCrashLoss",
    "TeacherDistillLoss",
    "kl_estimate",
]
