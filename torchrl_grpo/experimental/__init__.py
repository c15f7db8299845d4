"""Research variants beside the library: no API promise, the core never imports this package.

Importing it registers the experimental algorithm ``algo=grpo_lab``
(:mod:`torchrl_grpo.experimental.grpo_lab`): GRPO whose every setting is a key,
including those the recommended recipes fix (``roots=continue``, per-step returns,
ensembles, the cross-entropy group fit, ...). ``scripts/train.py`` and
``scripts/evaluate.py`` import it, so ``python scripts/train.py algo=grpo_lab
model=lab algo.roots=continue`` runs. ``docs/lab/`` holds what was measured with it.
"""

from torchrl_grpo.experimental.group_distill import GroupDistillLoss
from torchrl_grpo.experimental.grpo_lab import GRPOLab, GRPOLabConfig
from torchrl_grpo.experimental.prior import PriorLogits

__all__ = ["GRPOLab", "GRPOLabConfig", "GroupDistillLoss", "PriorLogits"]
