"""A residual policy: a network's logits plus a bonus on a base policy's action.

GRPO for language models starts from a supervised model and learns where to deviate
from it; :class:`PriorLogits` gives a driving policy the same start without spending
frames on behaviour cloning. The base policy (a scripted driver) adds ``weight`` to the
logit of the action it would take, so the initial policy plays it with probability
``e^w / (e^w + n - 1)`` and its greedy action is the base policy's wherever the
network's outputs are smaller than ``weight``. Training moves only the network: to
override the base policy in a state it must learn a margin of ``weight`` there.

``model=lab``'s ``model.prior`` and ``model.prior_weight``: :func:`prior_wrapper` is
registered with :func:`~torchrl_grpo.training.model_builder.register_policy_wrapper` when
this module is imported (``import torchrl_grpo.experimental``).
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import EnvBase

from torchrl_grpo.training.choices import choice_enum
from torchrl_grpo.training.model_builder import (
    BasePolicyName,
    make_base_policy,
    register_policy_wrapper,
)

__all__ = ["PriorLogits", "PriorName", "check_prior", "prior_wrapper"]

#: The scripted base policy whose action the policy's logits favour (``model.prior``).
PriorName: Any = choice_enum(
    "PriorName",
    BasePolicyName,
    "Scripted base policy whose action the policy's logits favour (``model.prior``).",
    module=__name__,
)


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


@register_policy_wrapper
def prior_wrapper(model_cfg: DictConfig, env: EnvBase, net: nn.Module, n_actions: int) -> nn.Module:
    """``net`` in a :class:`PriorLogits` of ``model.prior`` (``net`` itself without one).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import KinematicsMLP
        >>> cfg = OmegaConf.create({"prior": "rule", "prior_weight": 2.0})
        >>> type(prior_wrapper(cfg, HighwayEnv(seed=0), KinematicsMLP(5, 5, 5), 5)).__name__
        'PriorLogits'
    """
    prior = model_cfg.get("prior")
    if prior is None:
        return net
    base = make_base_policy(str(prior), env, "model.prior")
    return PriorLogits(net, base, n_actions, float(model_cfg.prior_weight))


def check_prior(model_cfg: DictConfig) -> None:
    """Refuses a ``model.prior_weight`` that is not positive, naming the key.

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_prior(OmegaConf.create({"prior": "rule", "prior_weight": 0.0}))
        Traceback (most recent call last):
        ...
        ValueError: model.prior_weight must be > 0, got 0.0
    """
    weight = model_cfg.get("prior_weight")
    if weight is not None and not weight > 0:
        raise ValueError(f"model.prior_weight must be > 0, got {weight}")
