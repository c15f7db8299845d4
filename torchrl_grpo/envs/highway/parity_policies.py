"""The parity ladder's policies: who records its worlds and who drives its episodes.

Example:
    >>> sorted(ladder_policies("highway-fast-v0", {}))
    ['drive', 'idle', 'random', 'rule', 'slower']
"""

from __future__ import annotations

from collections.abc import Callable

from tensordict import TensorDictBase

from torchrl_grpo.modules import (
    ConstantActionPolicy,
    KinematicsLayout,
    RandomPolicy,
    make_scripted_policy,
)
from torchrl_grpo.modules.scripted.actions import LONGITUDINAL_ACTIONS

__all__ = ["ladder_policies", "recording_policies"]

Policy = Callable[[TensorDictBase], TensorDictBase]


def ladder_policies(scenario: str, config: dict, seed: int = 1) -> dict[str, Policy]:
    """The ladder's policies by name: rung d's reference runs, and rung c's ``drive``.

    ``idle``, ``slower``, ``random`` (seeded with ``seed``) and ``rule`` (the rule
    policy), which also drives rung c; intersection-v0, whose actions are longitudinal
    only, has ``faster`` (always-FASTER) instead of ``rule``, and drives rung c with
    ``random``.

    Example:
        >>> sorted(ladder_policies("intersection-v0", {}))
        ['drive', 'faster', 'idle', 'random', 'slower']
    """
    if scenario == "intersection-v0":
        policies = {k: ConstantActionPolicy(a) for k, a in LONGITUDINAL_ACTIONS.items()}
        policies["random"] = RandomPolicy(len(LONGITUDINAL_ACTIONS), seed=seed)
        return {**policies, "drive": policies["random"]}
    rule = make_scripted_policy("rule", KinematicsLayout.from_highway_config(config))
    return {
        "idle": make_scripted_policy("idle"),
        "slower": make_scripted_policy("slower"),
        "random": make_scripted_policy("random", seed=seed),
        "rule": rule,
        "drive": rule,
    }


def recording_policies(scenario: str, config: dict) -> list[Policy]:
    """The policies whose highway-env runs record the ladder's worlds, in turn.

    The rule policy, random actions and always-FASTER (intersection-v0: always-FASTER,
    random actions and always-IDLE).

    Example:
        >>> len(recording_policies("intersection-v0", {}))
        3
    """
    if scenario == "intersection-v0":
        return [ConstantActionPolicy(2), RandomPolicy(3, seed=0), ConstantActionPolicy(1)]
    rule = make_scripted_policy("rule", KinematicsLayout.from_highway_config(config))
    return [rule, RandomPolicy(seed=0), ConstantActionPolicy(3)]
