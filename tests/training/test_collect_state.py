"""collector_state / load_collector_state: exact GRPO resumes, checkpoints of either format."""

from __future__ import annotations

import copy
from typing import Any

import pytest
import torch

from torchrl_grpo.branching import GroupCollector
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import RandomPolicy
from torchrl_grpo.training.collect import collector_state, load_collector_state

# The state_dict() keys of the root sources and the attributes the checkpoints written
# before they were complete (until issue 19) read instead.
_ATTRIBUTES = {"seed": "seed", "trunk_steps": "trunk_steps", "queue": "_queue", "live": "_live"}


def build(roots: str) -> GroupCollector:
    return GroupCollector(
        HighwayEnv("highway-fast-v0"),
        RandomPolicy(seed=0),
        group_size=2,
        horizon=2,
        groups_per_batch=1,
        roots=roots,
        decision_interval=2,
        select="sampled",
        seed=0,
    )


def old_format(collector: GroupCollector) -> dict[str, Any]:
    """What collector_state wrote before root sources had a complete state_dict().

    The collector's state_dict() held the root source's counters only (``{}`` for
    trunks, ``episodes_finished`` for continued episodes), and the rest of the source
    was read from its attributes into ``"source"``.
    """
    state = copy.deepcopy(collector.state_dict())
    source = state["root_source"]
    state["root_source"] = {k: source[k] for k in ("episodes_finished",) if k in source}
    extra = {_ATTRIBUTES[k]: v for k, v in source.items() if k in _ATTRIBUTES}
    if "episodes_finished" in source:
        extra["episodes_finished"] = source["episodes_finished"]
    return {"kind": "group", "state": state, "source": extra}


def resume(state: dict[str, Any], roots: str, policy_rng: torch.Tensor) -> list:
    with build(roots) as resumed:
        load_collector_state(resumed, state)
        resumed.policy.module.generator.set_state(policy_rng)
        return [next(iter(resumed)) for _ in range(3)]


@pytest.mark.parametrize("roots", ["reset", "trunk", "continue"])
def test_checkpoints_of_both_formats_resume_exactly(roots):
    with build(roots) as collector:
        next(iter(collector))
        new, old = collector_state(collector), old_format(collector)
        policy_rng = collector.policy.module.generator.get_state()
        want = [next(iter(collector)) for _ in range(3)]  # the reference: going on
    assert "source" not in new  # the root source's state is in the collector's
    assert "seed" in new["state"]["root_source"]
    if roots == "trunk":
        assert old["source"]["_queue"].shape[0] > 0  # a decision point still queued
    for state in (new, old):
        got = resume(state, roots, policy_rng)
        for g, w in zip(got, want, strict=True):
            assert torch.equal(g["group_id"], w["group_id"])
            assert torch.equal(g["root_step"], w["root_step"])
            assert torch.equal(g["observation"], w["observation"])
    # The control: the old format without its "source" part does not resume exactly.
    del old["source"]
    got = resume(old, roots, policy_rng)
    same = [torch.equal(g["observation"], w["observation"]) for g, w in zip(got, want, strict=True)]
    assert not all(same)


def test_a_checkpoint_of_another_kind_is_refused():
    with build("reset") as collector:
        with pytest.raises(ValueError, match="PPO"):
            load_collector_state(collector, {"kind": "torchrl"})
