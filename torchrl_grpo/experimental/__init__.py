"""Research variants beside the library: no API promise, the core never imports this package.

Importing it registers the experimental algorithm ``algo=grpo_lab``
(:mod:`torchrl_grpo.experimental.grpo_lab`): GRPO whose every setting is a key,
including those the recommended recipes fix, and plugs the variants no recipe uses into
the core's extension points:

* :mod:`~torchrl_grpo.experimental.prior`: ``model.prior``, a scripted policy's action
  favoured in the logits (a policy wrapper of ``make_policy``);
* :mod:`~torchrl_grpo.experimental.group_distill`: ``algo.group_fit_loss=cross_entropy``
  and ``algo.group_fit_weighting=spread`` (a group fit and a weighting by name);
* :mod:`~torchrl_grpo.experimental.lagging_tail`: ``algo.tail_sync_batches``;
* :mod:`~torchrl_grpo.experimental.trunk_clock`: ``algo.trunk=greedy``,
  ``rollout.first_root_step``, ``rollout.full_horizon_roots``;
* :mod:`~torchrl_grpo.experimental.neighbour_features`: ``model=lab
  model.kind=neighbours``, the network over every nearby lane's neighbours (a network
  kind registered with ``register_network_kind``).

``scripts/train.py`` and ``scripts/evaluate.py`` import it, so ``python scripts/train.py
algo=grpo_lab model=lab algo.roots=continue`` runs. ``docs/lab/`` holds what was measured
with it.
"""

from torchrl_grpo.experimental.group_distill import GroupDistillLoss
from torchrl_grpo.experimental.grpo_lab import GRPOLab, GRPOLabConfig
from torchrl_grpo.experimental.neighbour_features import NeighbourMLP
from torchrl_grpo.experimental.prior import PriorLogits

__all__ = [
    "GRPOLab",
    "GRPOLabConfig",
    "GroupDistillLoss",
    "NeighbourMLP",
    "PriorLogits",
]
