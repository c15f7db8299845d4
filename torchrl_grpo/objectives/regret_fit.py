"""The group fit by expected regret (``algo.group_fit_loss=regret``, merge-v0's recipe).

A group that tries every first action from one root and then follows a fixed policy
scores each action: its regret is the group's best advantage less the action's
(:func:`~torchrl_grpo.objectives.group_targets.group_regret`). The expected regret of
the policy at the root, ``sum_a pi(a|s) regret(a)``, weighs the root by what a wrong
action costs there: a crash's regret counts as much as the crash costs, a tie nothing.
Alone it settles on one action everywhere, since an action the policy gives no
probability gets no gradient; a tenth of the cross-entropy to the group's best actions
(:data:`ANCHOR`) keeps every best action within reach.

On merge-v0 the cross-entropy to the best set alone takes the search's speed and not
its caution (twice always-SLOWER's crashes), and this fit beats always-SLOWER
(docs/lab/scenarios.md). The highway recipes regress the advantages instead
(:class:`~torchrl_grpo.objectives.AdvantageRegressionLoss`).
"""

from __future__ import annotations

from dataclasses import dataclass

from tensordict import NestedKey, TensorDict, TensorDictBase

from torchrl_grpo.objectives.group_fit_loss import GroupFitLoss
from torchrl_grpo.objectives.loss_checks import check_finite, require

__all__ = ["ANCHOR", "GroupRegretLoss"]

#: Weight of the cross-entropy to the group's best actions beside the expected regret
#: (also the offline fit's, ``benchmarks/lab/label_inputs.py --loss regret``).
ANCHOR = 0.1


class GroupRegretLoss(GroupFitLoss):
    r"""Expected regret of the policy at each root, with a cross-entropy anchor.

    Each row is one branch's first step: its action ``a``, its regret and its weight
    ``w`` in its group's hard target (``1 / |best set|`` for a best action, else 0;
    :func:`~torchrl_grpo.objectives.group_targets.group_best_set`). The loss is
    ``coeff * (sum pi(a|s) regret + ANCHOR * sum -w log pi(a|s)) / sum w``: per root,
    the expected regret of the policy over its actions plus the anchor, averaged over
    the roots of the minibatch (``sum w`` counts them). A root weighting (the lab's
    ``algo.group_fit_weighting``) scales ``w``: it then weighs the anchor and the
    average, not each root's expected regret. Use it beside
    :class:`~torchrl_grpo.objectives.GRPOLoss`.

    Args:
        actor_network: the policy, as for
            :class:`~torchrl_grpo.objectives.group_fit_loss.GroupFitLoss`.

    Keyword Args:
        coeff: the weight of the term (``> 0``).

    Keys (change them with :meth:`set_keys`): ``action`` (``"action"``), ``regret``
    (``"distill_target"``) and ``target_weight`` (``"distill_weight"``).

    Outputs: ``loss_distill`` and the diagnostic ``distill_expected_regret`` (without
    ``coeff`` and the anchor).

    Example:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> net = TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"])
        >>> _ = torch.nn.init.zeros_(net.module.weight), torch.nn.init.zeros_(net.module.bias)
        >>> actor = ProbabilisticActor(net, ["logits"],
        ...                            distribution_class=torch.distributions.Categorical)
        >>> data = TensorDict(observation=torch.ones(2, 3), action=torch.tensor([0, 1]),
        ...                   distill_target=torch.tensor([0.0, 4.0]),
        ...                   distill_weight=torch.tensor([1.0, 0.0]), batch_size=[2])
        >>> out = GroupRegretLoss(actor, coeff=1.0)(data)
        >>> float(out["distill_expected_regret"])  # pi = 1/2 each: (0 + 4) / 2
        2.0
        >>> round(float(out["loss_distill"]), 4)  # 2 + 0.1 * log 2
        2.0693
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`GroupRegretLoss`, set with ``set_keys``.

        Attributes:
            action: the row's action (its branch's first action).
            target_weight: the row's weight in its group's hard target.
            regret: the row's regret (its group's best advantage less its own).
        """

        action: NestedKey = "action"
        target_weight: NestedKey = "distill_weight"
        regret: NestedKey = "distill_target"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_distill", "distill_expected_regret"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The loss over ``tensordict``'s rows (a flat batch)."""
        keys = self.tensor_keys
        weight = require(tensordict, keys.target_weight, "target_weight").reshape(-1)
        regret = require(tensordict, keys.regret, "regret").reshape(-1)
        action = require(tensordict, keys.action, "action")
        log_prob = self.actor_network.get_dist(tensordict).log_prob(action).reshape(-1)
        named = {repr(keys.target_weight): weight, repr(keys.regret): regret}
        check_finite({**named, "the policy's log-prob": log_prob})
        # A minibatch may hold none of its groups' best rows: then it counts one root.
        roots = weight.sum().clamp_min(1.0)
        expected = (log_prob.exp() * regret).sum() / roots
        anchor = -(weight * log_prob).sum() / roots
        return TensorDict(
            loss_distill=self.coeff * (expected + ANCHOR * anchor),
            distill_expected_regret=expected.detach(),
            batch_size=[],
        )
