"""evaluate_search: today's search, episode for episode, with all episodes at once."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from train_setup import compose_config

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import make_scripted_policy
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import evaluate, make_env, make_policy
from torchrl_grpo.training.search_eval import evaluate_search, search_policy
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
    [("racetrack-v0", "highway", "does not cover"), ("highway-fast-v0", "gpu", "'highway' or")],
)
def test_refusals_name_the_problem(scenario, on, match):
    cfg = OmegaConf.create({"scenario": scenario, "config": {}})
    with pytest.raises(ValueError, match=match):
        evaluate_search(cfg, DeterministicActor, 2, episodes=1, seed=0, on=on)


@pytest.mark.slow  # 21 s of highway-env steps; the default suite keeps its 10 minutes
def test_on_highway_env_it_plans_in_float64_where_float32_crashes():
    # roundabout-v0, seed 40048, the search over always-SLOWER to the episode's end: the
    # float32 planner's branches drift from highway-env's float64 episode on the ring and
    # the ego crashes at step 7 (measured); the default float64 planner, like the one-state
    # planner of search_policy, predicts the episode exactly and drives it to the end.
    cfg = OmegaConf.create({"scenario": "roundabout-v0", "config": {}})
    slower = make_scripted_policy("slower")
    kw = {"episodes": 1, "seed": 40_048, "max_steps": 20}
    exact = evaluate_search(cfg, slower, 11, **kw)
    rounded = evaluate_search(cfg, slower, 11, dtype=torch.float32, **kw)
    assert (exact.crashed, exact.lengths) == ([False], [11])
    assert (rounded.crashed, rounded.lengths) == ([True], [7])
    one_state, _ = evaluate(
        make_env(cfg, return_state=True), search_policy(cfg, slower, 11), name="one", **kw
    )
    assert one_state.returns == pytest.approx(exact.returns, abs=1e-6)
    assert one_state.crashed == exact.crashed
