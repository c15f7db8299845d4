"""Evaluation: fixed seeds, deterministic policy, baselines' numbers, table, plots."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict
from train_setup import compose_config, run_script

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import ConstantActionPolicy
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import evaluate, load_checkpoint, make_env, make_policy
from torchrl_grpo.training.config import typed_config
from torchrl_grpo.training.evaluation import evaluate_checkpoint
from torchrl_grpo.training.results import format_table


def _manual_return(action: int, seed: int, max_steps: int) -> tuple[float, bool, int]:
    """The same episode stepped by hand, independently of evaluate()."""
    env = HighwayEnv("highway-fast-v0")
    env.set_seed(seed)
    env.reset()
    total, crashed = 0.0, False
    for t in range(max_steps):
        out = env.step(TensorDict(action=torch.tensor(action)))["next"]
        total += float(out["reward"])
        crashed |= bool(out["crashed"])
        if bool(out["done"]):
            return total, crashed, t + 1
    return total, crashed, max_steps


def test_baselines_numbers_match_hand_rollouts(tmp_path):
    cfg = compose_config(
        [
            "env=highway_fast",
            "episodes=2",
            "seed=123",
            "baselines=[idle,slower]",
            "video=false",
            "env.max_episode_steps=12",
        ],
        config_name="evaluate",
    )
    report = evaluate_checkpoint(cfg, tmp_path)
    by_name = {r.name: r for r in report.results}
    assert set(by_name) == {"always-IDLE", "always-SLOWER"}
    for name, action in (("always-IDLE", 1), ("always-SLOWER", 4)):
        res = by_name[name]
        assert res.seeds == [123, 124]
        for i, seed in enumerate(res.seeds):
            ret, crashed, length = _manual_return(action, seed, 12)
            assert res.returns[i] == pytest.approx(ret, abs=1e-5)
            assert (res.crashed[i], res.lengths[i]) == (crashed, length)
    assert "always-SLOWER" in (tmp_path / "results.md").read_text()
    assert json.loads((tmp_path / "results.json").read_text())[0]["summary"]["episodes"] == 2
    assert (tmp_path / "comparison.png").stat().st_size > 0


def test_evaluation_is_repeatable_and_seed_dependent():
    env = HighwayEnv("highway-fast-v0")
    policy = ConstantActionPolicy("IDLE")
    a, _ = evaluate(env, policy, episodes=2, seed=5, max_steps=8)
    b, _ = evaluate(env, policy, episodes=2, seed=5, max_steps=8)
    c, _ = evaluate(env, policy, episodes=2, seed=50, max_steps=8)
    assert a.returns == b.returns
    assert a.returns != c.returns
    assert "| policy |" in format_table([a])


@pytest.mark.slow  # the default suite's 10-minute budget
def test_evaluate_script_on_a_checkpoint(smoke_run):
    train, run, _ = smoke_run
    assert train.returncode == 0, train.stderr[-3000:]
    proc = run_script(
        "evaluate.py",
        [f"checkpoint={run / 'last.pt'}", "episodes=1", "baselines=[slower]", "video=true"],
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "always-SLOWER" in proc.stdout and "grpo_branch" in proc.stdout
    # The paired verdict against each baseline; one episode has no standard error.
    verdict = next(line for line in proc.stdout.splitlines() if " vs always-SLOWER: " in line)
    assert "(paired, 1 episodes)" in verdict and verdict.endswith("does not beat always-SLOWER")
    assert (run / "eval" / "eval_episode.gif").stat().st_size > 0
    assert (run / "eval" / "results.md").exists()


# 28 s with its trained run; the planners also meet in tests/branching/test_batched_search.py
@pytest.mark.slow
def test_search_over_a_checkpoint_scores_as_the_planner_on_highway_env(smoke_run, tmp_path):
    train, run, _ = smoke_run
    assert train.returncode == 0, train.stderr[-3000:]
    cfg = compose_config(
        [f"checkpoint={run / 'last.pt'}", "episodes=2", "baselines=[slower]", "video=false"]
        + ["search_horizon=2"],
        config_name="evaluate",
    )
    report = evaluate_checkpoint(cfg, tmp_path)
    trained, searched, slower = report.results
    assert slower.name == "always-SLOWER"
    assert searched.name == "lookahead H=2 over the policy"
    # The reference: the same planner branching on highway-env's own snapshots.
    ckpt = load_checkpoint(run / "last.pt")
    run_cfg = typed_config(ckpt["config"])
    env = make_env(run_cfg.env, return_state=True)
    policy = make_policy(run_cfg.model, env)
    policy.load_state_dict(ckpt["policy"])
    planner = LookaheadPolicy(make_env(run_cfg.env), DeterministicActor(policy), horizon=2)
    seed = int(run_cfg.experiment.final_eval_seed)
    max_steps = int(run_cfg.env.max_episode_steps)
    reference, _ = evaluate(env, planner, episodes=2, seed=seed, max_steps=max_steps)
    assert searched.seeds == reference.seeds == trained.seeds
    assert searched.returns == pytest.approx(reference.returns, abs=1e-4)
    assert (searched.crashed, searched.lengths) == (reference.crashed, reference.lengths)
    # Paired verdicts: the policy against the search and the baseline, the search
    # against the baseline.
    table = (tmp_path / "results.md").read_text()
    assert " vs lookahead H=2 over the policy: " in table
    assert "\nlookahead H=2 over the policy vs always-SLOWER: " in table


@pytest.mark.parametrize(
    ("overrides", "match"),
    [(["search_horizon=-1", "checkpoint=x.pt"], ">= 0"), (["search_horizon=3"], "checkpoint")],
)
def test_search_horizon_refusals_name_the_problem(overrides, match, tmp_path):
    cfg = compose_config(["env=highway_fast", "video=false", *overrides], config_name="evaluate")
    with pytest.raises(ValueError, match=match):
        evaluate_checkpoint(cfg, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def _saved_run(overrides: list[str], path) -> tuple:
    """A fresh network saved as a run's checkpoint (its weights need no training)."""
    from torchrl_grpo.training.checkpoint import save_checkpoint
    from torchrl_grpo.training.config import to_container

    cfg = compose_config(["experiment=smoke", "model=mlp", *overrides])
    torch.manual_seed(3)
    policy = make_policy(cfg.model, make_env(cfg.env, seed=0))
    state = {"config": to_container(cfg), "policy": policy.state_dict(), "frames": 7}
    return save_checkpoint(state, path), cfg, policy


def test_another_runs_checkpoint_is_a_paired_baseline(tmp_path):
    path, run_cfg, policy = _saved_run([], tmp_path / "ppo_run" / "last.pt")
    cfg = compose_config(
        [f"checkpoint={path}", "episodes=2", "seed=40", f"baselines=[slower,'{path}']"]
        + ["video=false"],
        config_name="evaluate",
    )
    report = evaluate_checkpoint(cfg, tmp_path / "out")
    trained, slower, other = report.results
    assert slower.name == "always-SLOWER"
    assert other.name == "grpo_branch (7 frames, ppo_run)"
    # The reference: the same network driven greedily by hand on the same seeds.
    env = make_env(run_cfg.env)
    steps = int(run_cfg.env.max_episode_steps)
    reference, _ = evaluate(env, policy, episodes=2, seed=40, max_steps=steps)
    assert other.returns == trained.returns == reference.returns
    assert other.seeds == [40, 41]
    table = (tmp_path / "out" / "results.md").read_text()
    assert " vs grpo_branch (7 frames, ppo_run): return +0.00 ± 0.00 (paired, 2 episodes)" in table


@pytest.mark.parametrize(
    ("entry", "match"),
    [("slowr", "neither a scripted policy"), ("{merge}", "trained on merge-v0"), ("x.pt", "x.pt")],
)
def test_a_wrong_baselines_entry_fails_before_any_episode(entry, match, tmp_path):
    merge, _, _ = _saved_run(["env=merge"], tmp_path / "merge" / "last.pt")
    entry = entry.format(merge=merge)
    cfg = compose_config(
        ["env=highway_fast", "episodes=1", f"baselines=[slower,'{entry}']", "video=false"],
        config_name="evaluate",
    )
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        evaluate_checkpoint(cfg, tmp_path / "out")
    assert not (tmp_path / "out").exists()
