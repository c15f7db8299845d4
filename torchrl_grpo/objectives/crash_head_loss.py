"""The binary cross-entropy of a crash head: does this action, then the tail, crash?

Each trained row of an enumerated group is one branch's first step: its root's
observation, the action the branch took and whether the branch ended in a crash (the
env terminated it) within the horizon. A crash head
(:class:`~torchrl_grpo.modules.CrashHead`) predicts that for every action;
:class:`CrashHeadLoss` fits the row's action's prediction to the row's label.
"""

from __future__ import annotations

from dataclasses import dataclass

from tensordict import NestedKey, TensorDict, TensorDictBase
from torch import nn
from torchrl.objectives import LossModule

from torchrl_grpo.objectives.loss_checks import check_crash_head_args, check_finite, require

__all__ = ["CrashHeadLoss"]


class CrashHeadLoss(LossModule):
    r"""``coeff`` times the mean binary cross-entropy of each row's crash prediction.

    Args:
        head: a module whose ``crash_logits(observation)`` gives ``[*batch, n_actions]``
            logits of each action's crash probability (a
            :class:`~torchrl_grpo.modules.CrashHead`); used as it is, not copied.

    Keyword Args:
        coeff: the weight of the term (``> 0``).

    Keys (change them with :meth:`set_keys`): ``observation`` (``"observation"``),
    ``action`` (``"action"``) and ``label`` (``"branch_crashed"``: whether the row's
    branch ended in a crash, or a probability of it, such as
    :func:`~torchrl_grpo.objectives.survival.crash_label`'s).

    Outputs: ``loss_crash_head``, and the diagnostics ``crash_head_bce`` (without
    ``coeff``) and ``crash_head_accuracy`` (predictions on the label's side of 1/2).

    Example:
        >>> import torch
        >>> from torchrl_grpo.modules import CrashHead
        >>> net = torch.nn.Linear(3, 4)
        >>> torch.nn.init.zeros_(net.weight); torch.nn.init.zeros_(net.bias)
        Parameter containing:...
        >>> data = TensorDict(observation=torch.ones(2, 3), action=torch.tensor([0, 1]),
        ...                   branch_crashed=torch.tensor([True, False]), batch_size=[2])
        >>> out = CrashHeadLoss(CrashHead(net, 2), coeff=1.0)(data)
        >>> round(float(out["loss_crash_head"]), 4)  # p = 1/2 for both: log 2
        0.6931
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`CrashHeadLoss`, set with ``set_keys``.

        Attributes:
            observation: the head's input.
            action: the row's action (its branch's first action).
            label: whether the row's branch ended in a crash (bool), or its probability.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        label: NestedKey = "branch_crashed"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_crash_head", "crash_head_bce", "crash_head_accuracy"]

    def __init__(self, head: nn.Module, *, coeff: float) -> None:
        check_crash_head_args(head, coeff, "wrap the policy network in a CrashHead")
        super().__init__()
        self.head = head
        self.coeff = coeff

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        keys = self.tensor_keys
        return [keys.observation, keys.action, keys.label]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The mean cross-entropy over ``tensordict``'s rows (a flat batch)."""
        keys = self.tensor_keys
        observation = require(tensordict, keys.observation, "observation")
        action = require(tensordict, keys.action, "action").reshape(-1, 1).long()
        label = require(tensordict, keys.label, "label").reshape(-1).float()
        if bool(((label < 0) | (label > 1) | label.isnan()).any()):
            raise ValueError(f"the crash label {keys.label!r} must lie in [0, 1]")
        logits = self.head.crash_logits(observation).reshape(action.shape[0], -1)
        logit = logits.gather(-1, action).squeeze(-1)
        check_finite({"crash logits": logit})
        bce = nn.functional.binary_cross_entropy_with_logits(logit, label)
        accuracy = ((logit > 0) == (label > 0.5)).float().mean()
        return TensorDict(
            loss_crash_head=self.coeff * bce,
            crash_head_bce=bce.detach(),
            crash_head_accuracy=accuracy,
            batch_size=[],
        )
