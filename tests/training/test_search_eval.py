"""evaluate_search: today's search, episode for episode, with all episodes at once."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from train_setup import compose_config

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import make_env, make_policy
from torchrl_grpo.training.search_eval import evaluate_search
from torchrl_grpo.training.transfer import evaluate_on_tensor


def test_on_two_workers_it_gives_the_one_state_planners_table_on_the_tensor_simulator():
    cfg = compose_config(["experiment=smoke"])
    torch.manual_seed(0)
    policy = make_policy(cfg.model, make_env(cfg.env))  # untrained: it changes lanes, crashes
    planner = LookaheadPolicy(
        TensorHighwayEnv(cfg.env.scenario, num_envs=5), DeterministicActor(policy), horizon=2
    )
    # Today's search on the tensor simulator: the episodes as rows, each row's decision
    # one rollout of its 5 branches.
    env_cfg = OmegaConf.merge(cfg.env, {"max_episode_steps": 5})
    reference = evaluate_on_tensor(env_cfg, planner, episodes=3, seed=30_000, return_state=True)
    got = evaluate_search(
        env_cfg, policy, 2, episodes=3, seed=30_000, max_steps=5, on="tensor", workers=2
    )
    assert got.seeds == reference.seeds == [30_000, 30_001, 30_002]
    assert got.returns == pytest.approx(reference.returns, abs=1e-5)
    assert (got.lengths, got.crashed) == (reference.lengths, reference.crashed)
    assert got.speeds == pytest.approx(reference.speeds, abs=1e-5)


@pytest.mark.parametrize(
    ("scenario", "on", "match"),
    [("intersection-v0", "highway", "does not cover"), ("highway-fast-v0", "gpu", "'highway' or")],
)
def test_refusals_name_the_problem(scenario, on, match):
    cfg = OmegaConf.create({"scenario": scenario, "config": {}})
    with pytest.raises(ValueError, match=match):
        evaluate_search(cfg, DeterministicActor, 2, episodes=1, seed=0, on=on)
