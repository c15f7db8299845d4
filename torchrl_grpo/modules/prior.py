"""A residual policy: a network's logits plus a bonus on a base policy's action.

GRPO for language models starts from a supervised model and learns where to deviate
from it; :class:`PriorLogits` gives a driving policy the same start without spending
frames on behaviour cloning. The base policy (a scripted driver) adds ``weight`` to the
logit of the action it would take, so the initial policy plays it with probability
``e^w / (e^w + n - 1)`` and its greedy action is the base policy's wherever the
network's outputs are smaller than ``weight``. Training moves only the network: to
override the base policy in a state it must learn a margin of ``weight`` there.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

__all__ = ["PriorLogits"]


class PriorLogits(nn.Module):
    """``net(obs) + weight * one_hot(prior(obs))``: logits biased to a base policy's action.

    Args:
        net: the trained network, observation to ``[*batch, n_actions]`` logits.
        prior: the base policy. Either a module mapping the observation to int64
            actions ``[*batch]`` or a scripted policy (a :class:`TensorDictModule`
            around one, as :func:`~torchrl_grpo.modules.make_scripted_policy`
            returns). It must hold no trained parameters: it is not updated.
        n_actions: number of discrete actions.
        weight: logit bonus of the base policy's action (> 0).

    Raises:
        ValueError: ``weight`` is not positive, or ``prior`` has parameters.

    Example:
        >>> from torchrl_grpo.modules import KinematicsMLP, make_scripted_policy
        >>> net = KinematicsMLP(5, 5, out_features=5)
        >>> policy = PriorLogits(net, make_scripted_policy("slower"), 5, weight=3.0)
        >>> obs = torch.zeros(2, 5, 5)
        >>> bonus = policy(obs) - net(obs)
        >>> bonus.tolist()
        [[0.0, 0.0, 0.0, 0.0, 3.0], [0.0, 0.0, 0.0, 0.0, 3.0]]
    """

    def __init__(self, net: nn.Module, prior: nn.Module, n_actions: int, weight: float) -> None:
        super().__init__()
        if not weight > 0:
            raise ValueError(f"the prior's logit weight must be > 0, got {weight}")
        if isinstance(prior, TensorDictModule):
            prior = prior.module
        if next(prior.parameters(), None) is not None:
            raise ValueError(
                f"the prior {type(prior).__name__} has parameters; it must be a fixed "
                "policy (train the network instead)"
            )
        self.net = net
        self.prior = prior
        self.n_actions = int(n_actions)
        self.weight = float(weight)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` to ``[*batch, n_actions]`` logits."""
        logits = self.net(observation)
        with torch.no_grad():
            action = self.prior(observation)
        bonus = nn.functional.one_hot(action, self.n_actions).to(logits.dtype)
        return logits + self.weight * bonus
