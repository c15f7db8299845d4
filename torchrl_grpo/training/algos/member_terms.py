"""The loss of a policy ensemble: each member's own loss terms, averaged."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from torchrl_grpo.branching.keys import GROUP_ID
from torchrl_grpo.modules.ensemble import PolicyEnsemble, member_halves

__all__ = ["mean_member_terms"]


def mean_member_terms(
    ensemble: PolicyEnsemble,
    loss_terms: Callable[[TensorDictBase], TensorDictBase],
    minibatch: TensorDictBase,
    bagging: bool,
) -> TensorDictBase:
    """The mean over the members of ``loss_terms`` with each member acting alone.

    Each member gets the whole loss of its own outputs (its ratios, targets and crash
    predictions), so the members are fitted to the same data independently; the
    ensemble acts with their mean. With ``bagging``, member ``k`` gets the loss of the
    rows of its own half of the groups only (:func:`~torchrl_grpo.modules.ensemble.member_halves`).

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.modules.ensemble import PolicyEnsemble
        >>> ensemble = PolicyEnsemble([torch.nn.Linear(2, 3), torch.nn.Linear(2, 3)])
        >>> rows = TensorDict(x=torch.ones(4, 2), batch_size=[4])
        >>> def terms(td):
        ...     return TensorDict(loss_a=ensemble(td["x"]).sum())
        >>> mean = mean_member_terms(ensemble, terms, rows, bagging=False)
        >>> each = []
        >>> for k in range(2):
        ...     with ensemble.acting(k):
        ...         each.append(float(terms(rows)["loss_a"]))
        >>> bool(torch.isclose(mean["loss_a"], torch.tensor(sum(each) / 2)))
        True
    """
    halves = member_halves(minibatch.get(GROUP_ID), len(ensemble)) if bagging else None
    terms = []
    for member in range(len(ensemble)):
        rows = minibatch if halves is None else minibatch[halves[:, member]]
        if rows.shape[0] == 0:
            continue  # a small minibatch with none of this member's groups
        with ensemble.acting(member):
            terms.append(loss_terms(rows))
    mean = terms[0].empty()
    for key in terms[0].keys(include_nested=True, leaves_only=True):
        mean.set(key, torch.stack([t.get(key).float() for t in terms]).mean(0))
    return mean
