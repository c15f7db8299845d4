"""Training on the tensor simulator: a smoke run, its evaluation on highway-env, exact resume.

Also the evaluation's parts that come with it: the paired transfer gap, the baselines'
cache and the disjoint seed sets.
"""

from __future__ import annotations

import json

import pytest
import torch
from omegaconf import OmegaConf
from train_setup import TINY, compose_config, run_script

from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv
from torchrl_grpo.modules import ConstantActionPolicy, make_scripted_policy
from torchrl_grpo.training import (
    Trainer,
    evaluate,
    evaluate_baselines,
    load_checkpoint,
    make_env,
    make_policy,
)
from torchrl_grpo.training import baselines as baselines_module
from torchrl_grpo.training.config import check_config
from torchrl_grpo.training.env_builder import make_layout, make_rollout_env
from torchrl_grpo.training.group_schemas import MLPModelConfig
from torchrl_grpo.training.transfer import evaluate_on_tensor, paired_gap

TENSOR = ["env.backend=tensor", "env.num_envs=32"]


@pytest.mark.slow  # 17 s: a run, evaluated on both simulators
def test_a_tensor_smoke_run_trains_on_the_simulator_and_is_evaluated_on_highway_env(tmp_path):
    run_dir = tmp_path / "run"
    proc = run_script(
        "train.py",
        [
            "experiment=smoke",
            *TENSOR,
            "logger=csv",
            "experiment.total_frames=400",
            f"experiment.out_dir={run_dir}",
        ],
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "final evaluation:" in proc.stdout
    # Throughput and the transfer gap are logged beside the other metrics.
    [exp] = list((run_dir / "csv").iterdir())
    scalars = {p.stem for p in (exp / "scalars").rglob("*.csv")}
    logged = {"env_steps_per_s", "fps", "final_transfer_return_gap", "final_transfer_crash_gap"}
    assert logged <= scalars, scalars
    # The final evaluation drove highway-env itself: the saved policy, driven here by
    # hand on HighwayEnv from the final seeds, gives the same returns.
    ckpt = load_checkpoint(run_dir / "last.pt")
    cfg = OmegaConf.create(ckpt["config"])
    env = make_env(cfg.env)
    assert isinstance(env, HighwayEnv)
    policy = make_policy(cfg.model, env)
    policy.load_state_dict(ckpt["policy"])
    expected, _ = evaluate(
        env,
        policy,
        episodes=int(cfg.experiment.final_eval_episodes),
        seed=int(cfg.experiment.final_eval_seed),
        max_steps=int(cfg.env.max_episode_steps),
    )
    results = json.loads((run_dir / "results.json").read_text())["results"]
    assert results[0]["returns"] == expected.returns
    assert results[0]["seeds"] == expected.seeds
    assert [r["name"] for r in results[1:]] == ["always-SLOWER"]


@pytest.mark.parametrize(
    "live",
    [pytest.param(False, marks=pytest.mark.slow), True],
    ids=["queued_trunks", "live_staggered_trunks"],
)
def test_resume_on_the_tensor_simulator_continues_exactly(tmp_path, live):
    # How trunks run is a setting of the experimental algo=grpo_lab.
    common = [*TINY, *TENSOR, "algo=grpo_lab", f"rollout.live_trunks={live}"]
    common += ["experiment.checkpoint_every=1"]
    if live:
        # Spread, bounded trunks: a resumed run continues them, it does not spread them again.
        common += [
            "rollout.stagger_trunks=true",
            "rollout.full_horizon_roots=true",
            "rollout.first_root_step=4",
        ]

    def train(name, overrides):
        trainer = Trainer(compose_config([*common, *overrides]), run_dir=tmp_path / name)
        trainer.train()
        return trainer

    straight = train("straight", ["experiment.total_frames=700"])
    stopped = train("stopped", ["experiment.total_frames=300"])
    assert 0 < stopped.frames < straight.frames
    # No override but the budget: the rest comes from the checkpoint's config.
    path = tmp_path / "stopped" / "last.pt"
    cfg = compose_config([f"resume={path}", "experiment.total_frames=700"])
    assert cfg.env.backend == "tensor" and cfg.rollout.live_trunks == live
    assert cfg.rollout.stagger_trunks == live
    resumed = Trainer(cfg, run_dir=tmp_path / "resumed")
    resumed.train()
    assert (resumed.iteration, resumed.frames) == (straight.iteration, straight.frames)
    a, b = straight.policy.state_dict(), resumed.policy.state_dict()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # The control: the stopped run's parameters differ, so the check can fail.
    c = stopped.policy.state_dict()
    assert any(not torch.equal(a[k], c[k]) for k in a)


def _assert_same_episodes(tensor, highway, atol: float) -> None:
    """The same lengths and crashes, and returns within ``atol``."""
    assert tensor.lengths == highway.lengths and tensor.crashed == highway.crashed
    torch.testing.assert_close(
        torch.tensor(tensor.returns, dtype=torch.float64),
        torch.tensor(highway.returns, dtype=torch.float64),
        rtol=0,
        atol=atol,
    )


def test_the_transfer_gap_is_zero_for_a_scripted_policy_and_pairs_the_episodes():
    cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}, "max_episode_steps": 15})
    env = make_env(cfg)
    rule = make_scripted_policy("rule", make_layout(env))
    tensor = evaluate_on_tensor(cfg, rule, episodes=4, seed=300)
    highway, _ = evaluate(env, rule, episodes=4, seed=300, max_steps=15)
    # The simulator follows highway-env step by step: the same episodes, to float32.
    assert tensor.seeds == highway.seeds == list(range(300, 304))
    _assert_same_episodes(tensor, highway, atol=1e-4)
    gap = paired_gap(highway, tensor)
    assert abs(gap["return_gap"]) < 1e-4 and gap["crash_gap"] == 0.0
    # The control: another policy on the tensor side gives a gap.
    slower = evaluate_on_tensor(cfg, ConstantActionPolicy("SLOWER"), episodes=4, seed=300)
    assert abs(paired_gap(highway, slower)["return_gap"]) > 0.1
    with pytest.raises(ValueError, match="same episodes"):
        paired_gap(highway, evaluate_on_tensor(cfg, rule, episodes=4, seed=301))
    # In float64 the replay is highway-env's up to HighwayEnv's float32 rewards (1e-6,
    # where the float32 simulator needs 1e-4).
    exact = evaluate_on_tensor(cfg, rule, episodes=4, seed=300, dtype=torch.float64)
    _assert_same_episodes(exact, highway, atol=1e-6)


def test_a_network_drives_the_float64_simulator_on_float32_observations_as_on_highway_env():
    torch.manual_seed(0)
    cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}, "max_episode_steps": 15})
    env = make_env(cfg)
    policy = make_policy(OmegaConf.structured(MLPModelConfig), env)  # float32 weights
    highway, _ = evaluate(env, policy, episodes=4, seed=300, max_steps=15)
    exact = evaluate_on_tensor(cfg, policy, episodes=4, seed=300, dtype=torch.float64)
    _assert_same_episodes(exact, highway, atol=1e-5)  # returns: sums of float32 rewards


def test_the_transfer_gap_needs_a_config_the_simulator_covers():
    cfg = OmegaConf.create({"scenario": "racetrack-v0", "config": {}, "max_episode_steps": 5})
    with pytest.raises(ValueError, match="racetrack-v0"):
        evaluate_on_tensor(cfg, ConstantActionPolicy("IDLE"), episodes=1, seed=0)
    assert TensorHighwayEnv is not None


def test_baselines_are_evaluated_once_per_seed_set(tmp_path, monkeypatch):
    cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}, "max_episode_steps": 4})
    first = evaluate_baselines(cfg, ["slower", "idle"], episodes=2, seed=5, cache_dir=tmp_path)
    assert [r.name for r in first] == ["always-SLOWER", "always-IDLE"]
    assert len(list(tmp_path.iterdir())) == 2
    calls = []
    real = baselines_module.evaluate
    monkeypatch.setattr(
        baselines_module, "evaluate", lambda *a, **k: calls.append(k["seed"]) or real(*a, **k)
    )
    again = evaluate_baselines(cfg, ["slower", "idle"], episodes=2, seed=5, cache_dir=tmp_path)
    assert again == first and calls == []
    # Another seed set, or another config, is evaluated (and cached) anew.
    evaluate_baselines(cfg, ["slower"], episodes=2, seed=7, cache_dir=tmp_path)
    other = OmegaConf.merge(cfg, {"config": {"lanes_count": 3}})
    evaluate_baselines(other, ["slower"], episodes=2, seed=5, cache_dir=tmp_path)
    assert calls == [7, 5] and len(list(tmp_path.iterdir())) == 4


def test_the_periodic_and_final_evaluations_use_disjoint_seeds():
    overlap = compose_config(
        [
            *TINY,
            "experiment.final_eval_seed=10005",
            "experiment.eval_episodes=10",
            "experiment.final_eval_episodes=10",
        ]
    )
    with pytest.raises(ValueError, match="share 10005..10009"):
        check_config(overlap)
    cfg = compose_config([*TINY])
    periodic = set(range(cfg.experiment.eval_seed, cfg.experiment.eval_seed + 10))
    final = set(
        range(
            cfg.experiment.final_eval_seed,
            cfg.experiment.final_eval_seed + cfg.experiment.final_eval_episodes,
        )
    )
    assert not periodic & final


def test_the_lookahead_baseline_is_the_planner_over_the_rule_policy(tmp_path):
    from torchrl_grpo.branching import LookaheadPolicy

    cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}, "max_episode_steps": 2})
    [planner] = evaluate_baselines(cfg, ["lookahead"], episodes=1, seed=3, cache_dir=tmp_path)
    assert planner.name == "lookahead planner" and planner.lengths == [2]
    # The same episode planned by hand.
    env = make_env(cfg, return_state=True)
    rule = make_scripted_policy("rule", make_layout(env))
    by_hand = LookaheadPolicy(make_env(cfg), rule, horizon=baselines_module.LOOKAHEAD_HORIZON)
    expected, _ = evaluate(env, by_hand, episodes=1, seed=3, max_steps=2)
    assert planner.returns == expected.returns


def test_an_evaluation_on_the_tensor_simulator_leaves_the_training_rng_alone():
    cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}, "max_episode_steps": 3})
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    evaluate_on_tensor(cfg, ConstantActionPolicy("IDLE"), episodes=2, seed=5)
    assert torch.equal(torch.rand(3), expected)


def test_the_native_backend_trains_on_the_cpp_step_and_resumes_exactly(tmp_path):
    common = [*TINY, "env.backend=native", "env.num_envs=32", "experiment.checkpoint_every=1"]
    cfg = compose_config([*common, "experiment.total_frames=500"])
    assert make_rollout_env(cfg.env, cfg.rollout).step_mode == "native"
    straight = Trainer(cfg, tmp_path / "a")
    straight.train()
    stopped = Trainer(compose_config([*common, "experiment.total_frames=200"]), tmp_path / "b")
    stopped.train()
    assert 0 < stopped.frames < straight.frames
    cfg = compose_config([f"resume={tmp_path / 'b' / 'last.pt'}", "experiment.total_frames=500"])
    assert cfg.env.backend == "native"
    resumed = Trainer(cfg, run_dir=tmp_path / "c")
    resumed.train()
    assert resumed.frames == straight.frames
    a, b = straight.policy.state_dict(), resumed.policy.state_dict()
    assert all(torch.equal(a[key], b[key]) for key in a)


def test_the_native_backend_refuses_scenarios_without_a_cpp_step():
    cfg = OmegaConf.create({"scenario": "parking-v0", "config": {}, "backend": "native"})
    with pytest.raises(ValueError, match="env.backend=native.*parking-v0"):
        make_rollout_env(cfg, OmegaConf.create({"num_workers": 1, "backend": "single"}))
