"""Builders that turn a network into a TorchRL actor or critic.

Actors sample by default (``ExplorationType.RANDOM``), because GRPO groups and PPO
batches need sampled actions even from a plain ``env.rollout(policy=actor)``; for
evaluation, wrap the actor in :class:`DeterministicActor` or call it under
``torchrl.envs.utils.set_exploration_type(ExplorationType.DETERMINISTIC)``.
"""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import (
    IndependentNormal,
    OneHotCategorical,
    ProbabilisticActor,
    TanhNormal,
    ValueOperator,
)

from torchrl_grpo.modules.crash_head import acting_greedily

__all__ = [
    "ContinuousDistribution",
    "DeterministicActor",
    "make_continuous_actor",
    "make_discrete_actor",
    "make_value_net",
]

ContinuousDistribution = Literal["tanh_normal", "normal"]


def make_discrete_actor(
    net: nn.Module,
    action_spec: Categorical | OneHot | int,
    *,
    in_key: NestedKey = "observation",
    out_key: NestedKey = "action",
    default_interaction_type: ExplorationType = ExplorationType.RANDOM,
) -> ProbabilisticActor:
    """Wraps a logits network into a categorical :class:`ProbabilisticActor`.

    The network must map the observation to ``[*batch, n_actions]`` logits. The actor
    writes ``"logits"``, the action and its log-probability (``"action_log_prob"`` for
    the default ``out_key``; ``actor.log_prob_keys[0]`` in general).

    Args:
        net: the logits network.
        action_spec: the env's action spec, or a number of actions (an int64 index
            action, as highway-env's DiscreteMetaAction with categorical encoding). A
            :class:`~torchrl.data.OneHot` spec gives a one-hot actor.
        in_key: observation key read by the network.
        out_key: key of the sampled action.
        default_interaction_type: how to act when no exploration context is set.

    Returns:
        The actor.

    Example:
        >>> from torchrl_grpo.modules import KinematicsMLP
        >>> from tensordict import TensorDict
        >>> actor = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
        >>> td = actor(TensorDict(observation=torch.zeros(3, 5, 5), batch_size=[3]))
        >>> td["action"].shape, td["action_log_prob"].shape
        (torch.Size([3]), torch.Size([3]))
    """
    if isinstance(action_spec, int):
        action_spec = Categorical(action_spec)
    if isinstance(action_spec, OneHot):
        distribution_class: type = OneHotCategorical
    elif isinstance(action_spec, Categorical):
        distribution_class = torch.distributions.Categorical
    else:
        raise TypeError(
            f"make_discrete_actor needs a Categorical or OneHot spec, got {type(action_spec)}."
        )
    module = TensorDictModule(net, in_keys=[in_key], out_keys=["logits"])
    return ProbabilisticActor(
        module,
        in_keys=["logits"],
        out_keys=[out_key],
        spec=action_spec,
        distribution_class=distribution_class,
        return_log_prob=True,
        default_interaction_type=default_interaction_type,
    )


def make_continuous_actor(
    net: nn.Module,
    action_spec: Bounded | int,
    *,
    distribution: ContinuousDistribution = "tanh_normal",
    scale_mapping: str = "biased_softplus_1.0",
    scale_lb: float = 1e-4,
    in_key: NestedKey = "observation",
    out_key: NestedKey = "action",
    default_interaction_type: ExplorationType = ExplorationType.RANDOM,
) -> ProbabilisticActor:
    """Wraps a network into a Gaussian :class:`ProbabilisticActor`.

    The network must output ``2 * action_dim`` features; a
    :class:`~tensordict.nn.NormalParamExtractor` splits them into ``"loc"`` and a
    positive ``"scale"``.

    Args:
        net: network with ``2 * action_dim`` outputs.
        action_spec: the env's bounded action spec, or the action dimension (bounds
            then default to [-1, 1], those of highway-env's ContinuousAction).
        distribution: ``"tanh_normal"`` squashes samples into the spec's bounds;
            ``"normal"`` is an unbounded diagonal Gaussian (the env clips).
        scale_mapping: how raw outputs map to a positive scale (see
            :class:`~tensordict.nn.NormalParamExtractor`).
        scale_lb: lower bound of the scale.
        in_key: observation key read by the network.
        out_key: key of the sampled action.
        default_interaction_type: how to act when no exploration context is set.

    Returns:
        The actor.

    Example:
        >>> from torchrl_grpo.modules import KinematicsMLP
        >>> from tensordict import TensorDict
        >>> actor = make_continuous_actor(KinematicsMLP(5, 5, out_features=4), 2)
        >>> td = actor(TensorDict(observation=torch.zeros(3, 5, 5), batch_size=[3]))
        >>> td["action"].shape, bool(td["action"].abs().max() <= 1)
        (torch.Size([3, 2]), True)
    """
    if isinstance(action_spec, int):
        action_spec = Bounded(-1.0, 1.0, shape=(action_spec,))
    if not isinstance(action_spec, Bounded) and distribution == "tanh_normal":
        raise TypeError(f"tanh_normal needs a Bounded action spec, got {type(action_spec)}.")
    params = nn.Sequential(
        net, NormalParamExtractor(scale_mapping=scale_mapping, scale_lb=scale_lb)
    )
    module = TensorDictModule(params, in_keys=[in_key], out_keys=["loc", "scale"])
    if distribution == "tanh_normal":
        distribution_class: type = TanhNormal
        distribution_kwargs = {"low": action_spec.space.low, "high": action_spec.space.high}
    elif distribution == "normal":
        distribution_class = IndependentNormal
        distribution_kwargs = {}
    else:
        raise ValueError(f"Unknown distribution {distribution!r}.")
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=[out_key],
        spec=action_spec,
        distribution_class=distribution_class,
        distribution_kwargs=distribution_kwargs,
        return_log_prob=True,
        default_interaction_type=default_interaction_type,
    )


def make_value_net(
    net: nn.Module,
    *,
    in_key: NestedKey = "observation",
    out_key: NestedKey = "state_value",
) -> ValueOperator:
    """Wraps a network with one output into a :class:`ValueOperator` (PPO/GAE critic).

    Args:
        net: network mapping the observation to ``[*batch, 1]``, e.g.
            ``EgoAttentionNet(n_features, out_features=1)``.
        in_key: observation key read by the network.
        out_key: key of the value estimate.

    Returns:
        The critic.

    Example:
        >>> from torchrl_grpo.modules import EgoAttentionNet
        >>> from tensordict import TensorDict
        >>> critic = make_value_net(EgoAttentionNet(n_features=5, out_features=1))
        >>> critic(TensorDict(observation=torch.zeros(2, 5, 5), batch_size=[2]))[
        ...     "state_value"].shape
        torch.Size([2, 1])
    """
    return ValueOperator(net, in_keys=[in_key], out_keys=[out_key])


class DeterministicActor(TensorDictModuleBase):
    """Runs a policy under a fixed exploration type, whatever the caller's context.

    A collector wraps every policy call in ``set_exploration_type(RANDOM)`` by
    default; this wrapper sets the type inside the call, so evaluation through a
    collector or ``env.rollout`` acts greedily. It shares the wrapped actor's
    parameters.

    Args:
        policy: the actor to wrap.
        exploration_type: ``DETERMINISTIC`` (the distribution's own deterministic
            sample: the mode of a categorical, ``tanh(loc)`` rescaled for a
            TanhNormal) or ``MODE`` / ``MEAN``.

    Example:
        >>> from torchrl_grpo.modules import KinematicsMLP
        >>> from tensordict import TensorDict
        >>> actor = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
        >>> td = DeterministicActor(actor)(
        ...     TensorDict(observation=torch.zeros(2, 5, 5), batch_size=[2]))
        >>> bool((td["action"] == td["logits"].argmax(-1)).all())
        True
    """

    def __init__(
        self,
        policy: TensorDictModuleBase,
        exploration_type: ExplorationType = ExplorationType.DETERMINISTIC,
    ) -> None:
        super().__init__()
        if exploration_type == ExplorationType.RANDOM:
            raise ValueError("DeterministicActor cannot use ExplorationType.RANDOM.")
        self.policy = policy
        self.exploration_type = exploration_type
        self.in_keys = list(policy.in_keys)
        self.out_keys = list(policy.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Calls the wrapped policy under the fixed exploration type, acting greedily.

        Inside :func:`~torchrl_grpo.modules.crash_head.acting_greedily`: a crash head
        with a margin bars the actions riskier than SLOWER.
        """
        with set_exploration_type(self.exploration_type), acting_greedily():
            return self.policy(tensordict)
