"""Scripted policies by name: :data:`SCRIPTED_POLICIES` and :func:`make_scripted_policy`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.modules.scripted.actions import (
    IDLE,
    SLOWER,
    ConstantActionPolicy,
    RandomPolicy,
    ScriptedPolicy,
)
from torchrl_grpo.modules.scripted.policies import (
    AggressivePolicy,
    CautiousPolicy,
    ConservativePolicy,
    LaneChangePolicy,
    RulePolicy,
)

__all__ = ["SCRIPTED_POLICIES", "make_scripted_policy"]


def _idle(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return ConstantActionPolicy(IDLE, **kwargs)


def _slower(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return ConstantActionPolicy(SLOWER, **kwargs)


def _random(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return RandomPolicy(**kwargs)


def _left(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return LaneChangePolicy("left", layout, **kwargs)


def _right(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return LaneChangePolicy("right", layout, **kwargs)


#: Scripted policies by name. Each entry is called as ``factory(layout, **kwargs)``.
#: "aggressive", "conservative", "left", "right" and "cautious" are the five branch
#: policies of the original CARLA prototype demo.
SCRIPTED_POLICIES: dict[str, Callable[..., ScriptedPolicy]] = {
    "idle": _idle,
    "slower": _slower,
    "random": _random,
    "rule": RulePolicy,
    "aggressive": AggressivePolicy,
    "conservative": ConservativePolicy,
    "left": _left,
    "right": _right,
    "cautious": CautiousPolicy,
}


def make_scripted_policy(
    name: str, layout: KinematicsLayout | None = None, **kwargs: Any
) -> ScriptedPolicy:
    """Builds a scripted policy from :data:`SCRIPTED_POLICIES` by name.

    Args:
        name: a key of :data:`SCRIPTED_POLICIES`.
        layout: observation layout, for the policies that read the scene.
        **kwargs: forwarded to the policy's constructor.

    Returns:
        The policy.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> policy = make_scripted_policy("random", seed=0)
        >>> policy(TensorDict(observation=torch.zeros(3, 5, 5), batch_size=[3]))[
        ...     "action"].shape
        torch.Size([3])
    """
    try:
        factory = SCRIPTED_POLICIES[name]
    except KeyError:
        raise KeyError(
            f"Unknown scripted policy {name!r}; expected one of {sorted(SCRIPTED_POLICIES)}."
        ) from None
    return factory(layout, **kwargs)
