"""The policies of the parity ladder's tests (tests/envs/test_tensor_parity*.py, _native.py)."""

from __future__ import annotations

from torchrl_grpo.envs.highway import parity_policies


def recording_policies(config: dict, scenario: str = "highway-fast-v0") -> list:
    """The policies whose highway-env runs record the ladder's worlds (rule, random, FASTER)."""
    return parity_policies.recording_policies(scenario, config)


def reference_policies(config: dict, scenario: str = "highway-fast-v0") -> dict:
    """The policies scripts/highway_reference.py drove highway-env with, by name (rung d)."""
    policies = parity_policies.ladder_policies(scenario, config, seed=1)
    del policies["drive"]
    return policies
