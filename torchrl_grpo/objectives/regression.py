"""Regressing a group's comparison of actions: the policy's logits as advantage estimates.

A group that tries every action of a root once and then follows a fixed policy scores
each action exactly: its advantages are ``A(s, a) = Q(s, a) - mean_b Q(s, b)``. The
cross-entropy to ``softmax(A / tau)`` (the experimental
``torchrl_grpo.experimental.group_distill.GroupDistillLoss``) teaches, in states the
observation cannot tell apart, how often each action is the best; its greedy action is
then the one that wins most often, even where it crashes in the others. Regressing the
centred logits onto the advantages,
``tau * (l_a - mean_b l_b) ~ A(s, a)``, teaches the mean advantage of each action
over those states instead: the greedy action is the best on average, a crash in one
state in ten costing what it costs. Where the observation tells states apart, both
have the same optimum, ``pi(a|s) = softmax(A(s, a) / tau)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential

from torchrl_grpo.objectives.group_fit_loss import GroupFitLoss
from torchrl_grpo.objectives.loss_checks import check_finite, require

__all__ = ["AdvantageRegressionLoss"]


class AdvantageRegressionLoss(GroupFitLoss):
    r"""Weighted squared error of ``tau * (l_a - mean_b l_b)`` to each row's advantage.

    Each row is one branch's first step: its root's observation, the action ``a`` it
    took and the advantage ``A(s, a)`` its group gave it. The policy's logits ``l`` at
    that observation, centred over the actions and scaled by ``temperature``, estimate
    every action's advantage; the row's term is the squared error of its action's
    estimate. A group's rows together regress all of its root's actions. The loss is
    ``coeff * sum(w * err^2) / sum(w)`` over the rows, with ``w`` the row's weight
    (the same for all rows, or its group's spread). Use it beside
    :class:`~torchrl_grpo.objectives.GRPOLoss`.

    Args:
        actor_network: the categorical policy; its ``get_dist`` gives the logits. Its
            parameters are used as they are (not copied).

    Keyword Args:
        coeff: the weight of the term (``> 0``).
        temperature: ``tau > 0``, advantage units per logit: the policy it trains is
            ``softmax(A / tau)`` where states are told apart.

    Keys (change them with :meth:`set_keys`): ``action`` (``"action"``), ``target``
    (``"distill_target"``: the row's advantage, before any reweighting of the
    surrogate's) and ``weight`` (``"distill_weight"``).

    Outputs: ``loss_distill`` and the diagnostic ``distill_squared_error`` (the weighted
    mean squared error, without ``coeff``).

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
        ...                   distill_target=torch.tensor([-1.0, 1.0]),
        ...                   distill_weight=torch.ones(2), batch_size=[2])
        >>> loss = AdvantageRegressionLoss(actor, coeff=1.0, temperature=0.1)
        >>> float(loss(data)["loss_distill"])  # equal logits estimate 0 for both: error 1
        1.0
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`AdvantageRegressionLoss`, set with ``set_keys``.

        Attributes:
            action: the row's action (its branch's first action).
            target: the row's advantage in its group.
            weight: the row's weight in the loss.
        """

        action: NestedKey = "action"
        target: NestedKey = "distill_target"
        weight: NestedKey = "distill_weight"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_distill", "distill_squared_error"]

    def __init__(
        self, actor_network: ProbabilisticTensorDictSequential, *, coeff: float, temperature: float
    ) -> None:
        if not (temperature > 0 and temperature < float("inf")):
            raise ValueError(f"temperature must be a finite number > 0, got {temperature}")
        super().__init__(actor_network, coeff=coeff)
        self.temperature = temperature

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The weighted squared error of ``tensordict``'s rows (a flat batch)."""
        keys = self.tensor_keys
        weight = require(tensordict, keys.weight, "weight").reshape(-1)
        target = require(tensordict, keys.target, "target").reshape(-1)
        action = require(tensordict, keys.action, "action").reshape(-1, 1).long()
        logits = self.actor_network.get_dist(tensordict).logits
        logits = logits.reshape(action.shape[0], -1)
        check_finite({repr(keys.target): target, repr(keys.weight): weight, "logits": logits})
        centred = logits - logits.mean(-1, keepdim=True)
        estimate = self.temperature * centred.gather(-1, action).squeeze(-1)
        total = weight.sum().clamp_min(torch.finfo(weight.dtype).tiny)
        squared_error = (weight * (estimate - target).pow(2)).sum() / total
        return TensorDict(
            loss_distill=self.coeff * squared_error,
            distill_squared_error=squared_error.detach(),
            batch_size=[],
        )
