"""What the group fits' losses share: a policy, a weight, and keys read per row.

A group fit is a loss beside :class:`~torchrl_grpo.objectives.GRPOLoss` whose rows are
the first steps of an enumerated group's branches, each carrying its root's targets
(:class:`~torchrl_grpo.objectives.AdvantageRegressionLoss`,
:class:`~torchrl_grpo.objectives.GroupRegretLoss`, and the lab's cross-entropy fit).
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

from tensordict import NestedKey
from tensordict.nn import ProbabilisticTensorDictSequential
from torchrl.objectives import LossModule

__all__ = ["GroupFitLoss"]


class GroupFitLoss(LossModule):
    """Base of the group fits: the policy, the term's weight, and its ``_AcceptedKeys``.

    A subclass declares ``_AcceptedKeys`` (every field a key it reads per row) and
    ``forward``; its ``in_keys`` are the policy's and those keys.

    Args:
        actor_network: the policy; its ``get_dist`` gives the distribution. Its
            parameters are used as they are (not copied), so an optimiser over the
            GRPO loss's parameters trains this term too.

    Keyword Args:
        coeff: the weight of the term (``> 0``).

    Raises:
        ValueError: ``coeff`` is not a finite number ``> 0``.

    Example:
        >>> from torchrl_grpo.objectives import GroupRegretLoss
        >>> from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor
        >>> loss = GroupRegretLoss(make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5),
        ...                        coeff=1.0)
        >>> loss.in_keys
        ['observation', 'action', 'distill_weight', 'distill_target']
    """

    _AcceptedKeys: Any

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, *, coeff: float) -> None:
        if not (coeff > 0 and coeff < float("inf")):
            raise ValueError(f"coeff must be a finite number > 0, got {coeff}")
        super().__init__()
        self.actor_network = actor_network
        self.coeff = coeff

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        own = [getattr(self.tensor_keys, f.name) for f in fields(self.tensor_keys)]
        return list(dict.fromkeys([*self.actor_network.in_keys, *own]))
