"""Scripted policies on intersection-v0's longitudinal actions (0 SLOWER, 1 IDLE, 2 FASTER)."""

from __future__ import annotations

import pytest

from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv
from torchrl_grpo.training.evaluation import baseline_policy
from torchrl_grpo.training.model_builder import make_base_policy


@pytest.mark.parametrize(("name", "action"), [("slower", 0), ("idle", 1), ("faster", 2)])
def test_constant_policies_speak_the_three_actions(name, action):
    env = TensorHighwayEnv("intersection-v0", num_envs=2, seed=0)
    td = env.reset()
    for policy in (make_base_policy(name, env, "algo.tail_policy"), baseline_policy(name, None, 3)):
        assert policy(td.clone())["action"].tolist() == [action, action]
    # always-SLOWER stops before the crossing: highway-env's own episode earns nothing.
    if name == "slower":
        hw = HighwayEnv("intersection-v0", seed=0)
        out = hw.rollout(13, make_base_policy(name, hw, "baseline"))
        assert float(out["next", "reward"].sum()) == 0.0


def test_a_lane_changing_policy_is_refused_naming_the_key():
    env = TensorHighwayEnv("intersection-v0", num_envs=1, seed=0)
    with pytest.raises(ValueError, match="algo.tail_policy=rule.*3 actions"):
        make_base_policy("rule", env, "algo.tail_policy")
    assert baseline_policy("rule", None, 3) is None
