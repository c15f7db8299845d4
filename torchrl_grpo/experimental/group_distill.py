"""Distilling a group's comparison of actions: a soft target per root and its cross-entropy.

A group whose branches each take a different first action from the same root and then
follow a fixed policy scores every action of that root: its advantages are
``Q(s, a) - mean_a Q(s, a)``. The clipped surrogate moves each state's probabilities by
at most the clip ratio per update, however costly the wrong action is. The cross-entropy
to ``q(a|s) = softmax(A(s, a) / tau)`` (MPO's non-parametric target, here exact because
every action was tried) pulls the policy towards the group's best action on every
update, hardest where one action is much better than the others.

``algo=grpo_lab``'s ``algo.group_fit_loss=cross_entropy`` and
``algo.group_fit_weighting=spread``: importing this module registers them with the
core's GRPO (:func:`~torchrl_grpo.training.algos.enumerated.register_group_fit`,
:func:`~torchrl_grpo.training.algos.enumerated.register_group_fit_weighting`). The
recipes fit each root by regression (:class:`~torchrl_grpo.objectives.AdvantageRegressionLoss`)
or by expected regret (:class:`~torchrl_grpo.objectives.GroupRegretLoss`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torch import nn
from torchrl.objectives import LossModule

from torchrl_grpo.branching.keys import GROUP_ID
from torchrl_grpo.objectives.group_fit_loss import GroupFitLoss
from torchrl_grpo.objectives.group_targets import group_best_set, group_reduce, group_regret
from torchrl_grpo.objectives.loss_checks import check_finite, require
from torchrl_grpo.training.algos.enumerated import (
    GroupFit,
    register_group_fit,
    register_group_fit_weighting,
)
from torchrl_grpo.training.algos.grpo_config import GroupFit as CoreGroupFit
from torchrl_grpo.training.choices import choice_enum

__all__ = [
    "GroupDistillLoss",
    "GroupFitLossName",
    "GroupFitWeightingName",
    "group_softmax_target",
    "group_spread",
]

#: What the group fit fits (``algo.group_fit_loss``): each root's softmax target by
#: cross-entropy, or one of the core's fits (its advantages by the policy's centred
#: logits, the highway recipes'; the policy's expected regret, merge-v0's).
LabGroupFit = Literal["cross_entropy", CoreGroupFit]
#: Weight of each root in the group fit (``algo.group_fit_weighting``): the same for
#: all (the recipes'), or its group's spread (best minus worst advantage).
GroupFitWeighting = Literal["uniform", "spread"]
GroupFitLossName: Any = choice_enum(
    "GroupFitLossName", LabGroupFit, "What the group fit fits.", module=__name__
)
GroupFitWeightingName: Any = choice_enum(
    "GroupFitWeightingName",
    GroupFitWeighting,
    "Weight of a root in the group fit.",
    module=__name__,
)


def group_softmax_target(
    advantage: torch.Tensor, group_id: torch.Tensor, temperature: float
) -> torch.Tensor:
    """Each row's weight in its group's target: ``softmax(advantage / temperature)`` per group.

    Rows are the branches' first steps, one per enumerated action. Within every group
    the weights sum to 1. ``temperature=0`` gives the hard target: the group's best
    rows share the weight equally.

    Args:
        advantage: one advantage per row, ``[N]`` or ``[N, 1]``.
        group_id: the integer id of each row's root, ``[N]``.
        temperature: ``tau >= 0``, in the advantage's units (returns for unscaled
            advantages).

    Returns:
        The weights, shaped like ``advantage``.

    Raises:
        ValueError: a negative or non-finite temperature, or shapes that disagree.

    Example:
        >>> import torch
        >>> adv = torch.tensor([0.0, 1.0, 1.0, -2.0, 2.0])
        >>> gid = torch.tensor([0, 0, 0, 1, 1])
        >>> group_softmax_target(adv, gid, 0.0)
        tensor([0.0000, 0.5000, 0.5000, 0.0000, 1.0000])
        >>> group_softmax_target(adv, gid, 1.0).round(decimals=3)
        tensor([0.1550, 0.4220, 0.4220, 0.0180, 0.9820])
    """
    if not (temperature >= 0 and temperature < float("inf")):
        raise ValueError(f"temperature must be a finite number >= 0, got {temperature}")
    if temperature == 0:
        return group_best_set(advantage, group_id)
    # Shifted by the group's best: exp never overflows, the best row scores 1.
    score = (-group_regret(advantage, group_id) / temperature).exp()
    return score / group_reduce(score, group_id, "sum")


def group_spread(advantage: torch.Tensor, group_id: torch.Tensor) -> torch.Tensor:
    """Each row's group spread: its group's best advantage minus its worst.

    A root whose actions all score alike (spread 0) has nothing to teach; one where an
    action crashes and another does not has a spread of the crash's cost. Used as a
    root's weight in the distillation (``algo.group_fit_weighting=spread``).

    Args:
        advantage: one advantage per row, ``[N]`` or ``[N, 1]``.
        group_id: the integer id of each row's root, ``[N]``.

    Returns:
        The spreads, shaped like ``advantage`` (equal within a group, ``>= 0``).

    Raises:
        ValueError: shapes that disagree.

    Example:
        >>> import torch
        >>> adv = torch.tensor([0.0, 1.0, -3.0, 2.0, 2.0])
        >>> group_spread(adv, torch.tensor([0, 0, 0, 1, 1]))
        tensor([4., 4., 4., 0., 0.])
    """
    best = group_reduce(advantage, group_id, "amax")
    return best - group_reduce(advantage, group_id, "amin")


class GroupDistillLoss(GroupFitLoss):
    r"""Cross-entropy from each root's group target to the policy: ``-sum_a q(a|s) log pi(a|s)``.

    Each row is one branch's first step and carries its weight ``q(a|s)`` in its
    group's target (:func:`group_softmax_target`), so the row's term is
    ``-q(a|s) log pi(a|s)``; a group's rows add up to the cross-entropy of its root.
    The loss is their weighted mean, ``coeff * sum(-q log pi) / sum(q)``, so a
    minibatch of whole groups gives ``coeff`` times the mean cross-entropy per root; a
    minibatch whose rows all have weight 0 gives 0.
    Use it beside :class:`~torchrl_grpo.objectives.GRPOLoss`.

    Args:
        actor_network: the policy, as for
            :class:`~torchrl_grpo.objectives.group_fit_loss.GroupFitLoss`.

    Keyword Args:
        coeff: the weight of the term (``> 0``).

    Keys (change them with :meth:`set_keys`): ``action`` (``"action"``) and
    ``target_weight`` (``"distill_weight"``).

    Outputs: ``loss_distill`` and the diagnostic ``distill_cross_entropy`` (the
    weighted mean of ``-log pi(a|s)``, without ``coeff``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> net = TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"])
        >>> torch.nn.init.zeros_(net.module.weight); torch.nn.init.zeros_(net.module.bias)
        Parameter containing:...
        >>> actor = ProbabilisticActor(net, ["logits"],
        ...                            distribution_class=torch.distributions.Categorical)
        >>> data = TensorDict(observation=torch.ones(2, 3), action=torch.tensor([0, 1]),
        ...                   distill_weight=torch.tensor([1.0, 0.0]), batch_size=[2])
        >>> out = GroupDistillLoss(actor, coeff=1.0)(data)
        >>> round(float(out["loss_distill"]), 4)  # -log(1/2): uniform policy, hard target
        0.6931
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`GroupDistillLoss`, set with ``set_keys``.

        Attributes:
            action: the row's action (its branch's first action).
            target_weight: the row's weight ``q(a|s)`` in its group's target.
        """

        action: NestedKey = "action"
        target_weight: NestedKey = "distill_weight"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_distill", "distill_cross_entropy"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The weighted cross-entropy of ``tensordict``'s rows (a flat batch)."""
        keys = self.tensor_keys
        weight = require(tensordict, keys.target_weight, "target_weight").reshape(-1)
        action = require(tensordict, keys.action, "action")
        dist = self.actor_network.get_dist(tensordict)
        log_prob = dist.log_prob(action).reshape(-1)
        check_finite({repr(keys.target_weight): weight, "the policy's log-prob": log_prob})
        # A minibatch may hold none of its groups' best rows (hard targets): then the
        # term is 0, not an error that would stop a training run.
        total = weight.sum().clamp_min(torch.finfo(weight.dtype).tiny)
        cross_entropy = -(weight * log_prob).sum() / total
        return TensorDict(
            loss_distill=self.coeff * cross_entropy,
            distill_cross_entropy=cross_entropy.detach(),
            batch_size=[],
        )


def _cross_entropy_targets(data: TensorDictBase, temperature: float) -> torch.Tensor:
    return group_softmax_target(data.get("advantage"), data.get(GROUP_ID), temperature)


def _cross_entropy_loss(policy: nn.Module, coeff: float, temperature: float) -> LossModule:
    return GroupDistillLoss(policy, coeff=coeff)


register_group_fit("cross_entropy", GroupFit(_cross_entropy_targets, _cross_entropy_loss))
register_group_fit_weighting("spread", group_spread)
