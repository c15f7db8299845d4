"""The fit of a policy and its crash head to the lookahead search's labels of a state.

The search (:class:`~torchrl_grpo.branching.LookaheadPolicy`) tries every action of a
state and scores it by its branch's return; each branch also says whether it crashed.
:class:`SearchLabelLoss` fits a network with a crash head to both, at every action at
once: its policy to the search's best set, with the expected regret beside it, and its
crash head to the branches' crash flags.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torch import nn
from torch.nn import functional as F
from torchrl.objectives import LossModule

from torchrl_grpo.objectives.loss_checks import check_crash_head_args, check_finite, require

__all__ = ["BEST_SET_TOLERANCE", "SearchLabelLoss"]

#: Scores within this of a state's best one are in its best set: a tie of branch returns.
BEST_SET_TOLERANCE = 1e-6


class SearchLabelLoss(LossModule):
    r"""The best set's cross-entropy, the expected regret and the crash head's cross-entropy.

    For a state with search scores ``Q(a)`` and crash flags ``c(a)``, and the network's
    policy ``pi`` (its own logits, before the crash head weighs them) and crash
    probabilities ``p``:

    .. math::

        -\sum_a t(a) \log \pi(a)
        + \text{regret\_coeff} \sum_a \pi(a) (\max_b Q(b) - Q(a))
        + \text{crash\_coeff} \cdot \text{BCE}(p, c)

    with ``t`` uniform over the best set (the actions within :data:`BEST_SET_TOLERANCE`
    of the best score). The cross-entropy counts a near-tie lost as much as a crash
    taken; the regret weighs each state by what a wrong choice costs there
    (docs/lab/targets.md, "A finer fit").

    Args:
        head: the policy's :class:`~torchrl_grpo.modules.CrashHead` (its ``heads`` give
            the policy's own logits and the crash logits, its ``acted`` the logits it acts
            on); used as it is, not copied.

    Keyword Args:
        regret_coeff: the weight of the expected regret (``>= 0``).
        crash_coeff: the weight of the crash head's cross-entropy (``> 0``).

    Keys (change them with :meth:`set_keys`): ``observation`` (``"observation"``),
    ``scores`` (``"search_scores"``) and ``crashed`` (``"search_crashed"``).

    Outputs: ``loss_best_set``, ``loss_search_regret``, ``loss_search_crash``, and the
    diagnostics, for the actions the policy acts on greedily (its logits weighed by the
    crash head): ``search_accuracy`` (in the best set), ``search_regret`` (what they
    lose to the best branch) and ``search_crash_error`` (the share of states where
    their branch crashes and another's does not).

    Example:
        >>> import math
        >>> from torchrl_grpo.modules import CrashHead
        >>> net = nn.Linear(3, 4)
        >>> _ = nn.init.zeros_(net.weight), nn.init.zeros_(net.bias)
        >>> data = TensorDict(observation=torch.ones(1, 3),
        ...                   search_scores=torch.tensor([[1.0, 3.0]]),
        ...                   search_crashed=torch.tensor([[True, False]]), batch_size=[1])
        >>> out = SearchLabelLoss(CrashHead(net, 2), regret_coeff=1.0, crash_coeff=1.0)(data)
        >>> round(float(out["loss_best_set"]), 4) == round(math.log(2), 4)  # pi = (1/2, 1/2)
        True
        >>> float(out["loss_search_regret"])  # 1/2 of the 2 the first action loses
        1.0
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`SearchLabelLoss`, set with ``set_keys``.

        Attributes:
            observation: the network's input.
            scores: every action's branch return, ``[N, n_actions]``.
            crashed: whether every action's branch crashed, ``[N, n_actions]``.
        """

        observation: NestedKey = "observation"
        scores: NestedKey = "search_scores"
        crashed: NestedKey = "search_crashed"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = [
        "loss_best_set",
        "loss_search_regret",
        "loss_search_crash",
        "search_accuracy",
        "search_regret",
        "search_crash_error",
    ]

    def __init__(self, head: nn.Module, *, regret_coeff: float, crash_coeff: float) -> None:
        check_crash_head_args(head, crash_coeff, "the student needs model.crash_head=true")
        if not callable(getattr(head, "heads", None)) or not callable(getattr(head, "acted", None)):
            raise TypeError(f"{type(head).__name__} has no heads and acted: use a CrashHead")
        if not (regret_coeff >= 0 and regret_coeff < float("inf")):
            raise ValueError(f"regret_coeff must be a finite number >= 0, got {regret_coeff}")
        super().__init__()
        self.head = head
        self.regret_coeff = float(regret_coeff)
        self.crash_coeff = float(crash_coeff)

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        keys = self.tensor_keys
        return [keys.observation, keys.scores, keys.crashed]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The mean of each term over ``tensordict``'s rows (a flat batch)."""
        keys = self.tensor_keys
        observation = require(tensordict, keys.observation, "observation")
        scores = require(tensordict, keys.scores, "scores").float()
        crashed = require(tensordict, keys.crashed, "crashed")
        logits, crash = self.head.heads(observation)
        if scores.shape != logits.shape or crashed.shape != logits.shape:
            raise ValueError(
                f"the search labelled {tuple(scores.shape)} scores and {tuple(crashed.shape)} "
                f"crash flags; the policy has {tuple(logits.shape)} logits"
            )
        check_finite({"the search's scores": scores, "the policy's logits": logits})
        gap = scores.amax(-1, keepdim=True) - scores
        best = (gap <= BEST_SET_TOLERANCE).float()
        log_pi = logits.log_softmax(-1)
        cross_entropy = -((best / best.sum(-1, keepdim=True)) * log_pi).sum(-1).mean()
        regret = (log_pi.exp() * gap).sum(-1).mean()
        flags = crashed.float()
        bce = F.binary_cross_entropy_with_logits(crash, flags)
        with torch.no_grad():
            chosen = self.head.acted(logits, crash).argmax(-1, keepdim=True)
            lost = gap.gather(-1, chosen).squeeze(-1)
            into_crash = flags.gather(-1, chosen).squeeze(-1) > 0
            avoidable = (flags < 1).any(-1)
        return TensorDict(
            loss_best_set=cross_entropy,
            loss_search_regret=self.regret_coeff * regret,
            loss_search_crash=self.crash_coeff * bce,
            search_accuracy=(lost <= BEST_SET_TOLERANCE).float().mean(),
            search_regret=lost.mean(),
            search_crash_error=(into_crash & avoidable).float().mean(),
            batch_size=[],
        )
