"""Critic-free objectives: group-relative advantages, GRPOLoss, KL estimators, reference sync.

Also the group fits of enumerated groups' action comparisons: the regression of the
advantages (``AdvantageRegressionLoss``) and the policy's expected regret at each root
(``GroupRegretLoss``, with the per-root targets of ``group_targets.py``). And the loss of
a crash head (``CrashHeadLoss``) and the distillation of trained teachers into one policy
(``TeacherDistillLoss``, and ``TeacherCrashLoss`` for their crash heads), and the fit
of the lookahead search's labels (``SearchLabelLoss``). What the
losses share (the crash labels and tail survival of ``survival.py``, the ``Literal``
choices) is imported from its module.
"""

from torchrl_grpo.objectives.advantage import GroupRelativeAdvantage
from torchrl_grpo.objectives.bootstrap import HorizonBootstrap
from torchrl_grpo.objectives.crash_head_loss import CrashHeadLoss
from torchrl_grpo.objectives.grpo_loss import GRPOLoss
from torchrl_grpo.objectives.kl import kl_estimate
from torchrl_grpo.objectives.reference import ReferenceSync
from torchrl_grpo.objectives.regression import AdvantageRegressionLoss
from torchrl_grpo.objectives.regret_fit import GroupRegretLoss
from torchrl_grpo.objectives.search_label_loss import SearchLabelLoss
from torchrl_grpo.objectives.teacher_losses import TeacherCrashLoss, TeacherDistillLoss

__all__ = [
    "AdvantageRegressionLoss",
    "CrashHeadLoss",
    "GRPOLoss",
    "GroupRegretLoss",
    "GroupRelativeAdvantage",
    "HorizonBootstrap",
    "ReferenceSync",
    "SearchLabelLoss",
    "TeacherCrashLoss",
    "TeacherDistillLoss",
    "kl_estimate",
]
