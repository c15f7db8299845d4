"""The policies of the parity ladder's tests (tests/envs/test_tensor_parity*.py, _native.py)."""

from __future__ import annotations

from torchrl_grpo.modules import (
    ConstantActionPolicy,
    KinematicsLayout,
    RandomPolicy,
    make_scripted_policy,
)


def recording_policies(config: dict) -> list:
    """The policies whose highway-env runs record the ladder's worlds: rule, random, FASTER."""
    rule = make_scripted_policy("rule", KinematicsLayout.from_highway_config(config))
    return [rule, RandomPolicy(seed=0), ConstantActionPolicy(3)]


def reference_policies(config: dict) -> dict:
    """The policies scripts/highway_reference.py drove highway-env with, by name (rung d)."""
    layout = KinematicsLayout.from_highway_config(config)
    return {
        "idle": make_scripted_policy("idle"),
        "slower": make_scripted_policy("slower"),
        "random": make_scripted_policy("random", seed=1),
        "rule": make_scripted_policy("rule", layout),
    }
