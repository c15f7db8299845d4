"""Checkpoints written before the training/ split still load: resume, evaluate, their config.

The files of ``data/`` were written by the code before ``training/algos/`` (see
``data/README.md``): a GRPO run on trunk roots, one on continuation roots (its config
says ``roots: continuation``, today's ``continue``) and a PPO run.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from train_setup import ROOT, TINY, compose_config

import torchrl_grpo.experimental  # noqa: F401  (v1's GRPO runs read as algo=grpo_lab)
from torchrl_grpo.training import Trainer, evaluate, load_checkpoint, make_env, make_policy
from torchrl_grpo.training.algos.registry import with_fixed_settings
from torchrl_grpo.training.config import to_container, typed_config
from torchrl_grpo.training.evaluation import evaluate_checkpoint

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
# The overrides each run was written with (beside experiment=smoke, logger=none).
RUNS = {
    "grpo_branch": [],
    "grpo_continuation": ["algo.roots=continuation"],
    "ppo": ["algo=ppo"],
}


def _assert_equal_state(saved: dict, loaded: dict) -> None:
    assert saved.keys() == loaded.keys()
    for key, value in saved.items():
        assert torch.equal(value, loaded[key]), key


def _assert_equal_optimizer(saved: dict, loaded: dict) -> None:
    assert saved["param_groups"] == loaded["param_groups"]
    assert saved["state"].keys() == loaded["state"].keys()
    for index, state in saved["state"].items():
        for name, value in state.items():
            assert torch.equal(value, loaded["state"][index][name]), (index, name)


@pytest.mark.parametrize("run", sorted(RUNS))
def test_an_old_config_validates_against_todays_schemas(run):
    ckpt = load_checkpoint(DATA / f"v1_{run}.pt")
    cfg = typed_config(ckpt["config"])
    # v1's GRPO defaults (scale_rewards=group, sampled first actions, ...) are not the
    # settings the recipe fixes today: its runs read as the experimental grpo_lab's.
    schema = "PPOConfig" if run == "ppo" else "GRPOLabConfig"
    assert OmegaConf.get_type(cfg.algo).__name__ == schema
    model, old = OmegaConf.to_container(cfg.model), ckpt["config"]["model"]
    kept = {key: old[key] for key in old if key in model}
    assert {key: model[key] for key in kept} == kept
    if run == "ppo":
        # An MLP reads none of the attention sizes, and the prior was off: both retired.
        assert old.keys() - model.keys() == {
            "embed_dim",
            "num_heads",
            "encoder_cells",
            "decoder_cells",
            "prior",
            "prior_weight",
        }
    # Keys added since take defaults that keep the old behaviour: no crash head, one network.
    added = {key: model[key] for key in model.keys() - old.keys()}
    lab = {} if run == "ppo" else {"ensemble": 1, "bagging": False}
    assert added == {"crash_head": False, "crash_aversion": 0.0, "crash_margin": None, **lab}
    if run == "grpo_continuation":
        assert ckpt["config"]["algo"]["roots"] == "continuation"
        assert str(cfg.algo.roots) == "continue"
    # The run folder's config.yaml holds the same config.
    assert OmegaConf.load(DATA / f"v1_{run}.yaml") == OmegaConf.create(ckpt["config"])


def _main_before_the_keys_retired() -> dict:
    """The default run's config as main wrote it before #40 fixed the recipe's settings."""
    cfg = OmegaConf.to_container(with_fixed_settings(compose_config([])))
    algo = cfg["algo"]
    for key in ("coeff", "loss", "temperature", "weighting"):
        algo[f"distill_{key}"] = algo.pop(f"group_fit_{key}")
    cfg["experiment"] |= {"name": "default", "transfer_gap": True, "plot_every": 0}
    cfg["experiment"]["progress_bar"] = True
    cfg["logger"] |= {"group": None, "tags": [], "group_plots": True}
    ray = {"num_actors": 2, "workers_per_actor": 1, "env_backend": "single"}
    cfg["rollout"] |= {"frames_per_batch": 512, "ray": ray}
    cfg["model"] |= {"embed_dim": 64, "num_heads": 2, "encoder_cells": [64]}
    return cfg


def test_a_config_of_main_before_the_keys_retired_reads_as_todays_recipe():
    old = _main_before_the_keys_retired()
    assert old["algo"]["roots"] == "trunk" and old["optim"]["eps"] == 1e-8
    cfg = typed_config(old)
    assert OmegaConf.get_type(cfg.algo).__name__ == "GRPOConfig"
    assert to_container(cfg) == to_container(compose_config([]))
    # The control: one fixed setting with another value is a grpo_lab run.
    old["rollout"]["stagger_trunks"] = False
    lab = typed_config(old)
    assert str(lab.algo.name) == "grpo_lab" and lab.rollout.stagger_trunks is False


def test_a_config_of_main_before_the_group_fit_weight_retired_reads_as_todays_recipe():
    # Before #42 grpo_branch had algo.group_fit_coeff and no algo.group_fit_loss.
    old = to_container(compose_config(["env=merge"]))
    old["algo"]["group_fit_coeff"] = 1.0
    del old["algo"]["group_fit_loss"]
    cfg = typed_config(old)
    assert OmegaConf.get_type(cfg.algo).__name__ == "GRPOConfig"
    assert cfg.algo.group_fit_loss == "regression" and "group_fit_coeff" not in cfg.algo
    assert with_fixed_settings(cfg).algo.group_fit_coeff == 1.0
    # Another weight is a grpo_lab run, which keeps it.
    old["algo"]["group_fit_coeff"] = 0.5
    lab = typed_config(old)
    assert str(lab.algo.name) == "grpo_lab" and lab.algo.group_fit_coeff == 0.5
    assert lab.algo.group_fit_loss == "regression"  # as it ran


def test_a_retired_value_without_the_lab_is_refused_naming_the_key():
    # A fresh interpreter without torchrl_grpo.experimental imported.
    code = (
        "from torchrl_grpo.training.config import typed_config\n"
        "typed_config({'algo': {'name': 'grpo_branch', 'roots': 'continue'}})"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 1
    assert "algo.roots='continue' (grpo_branch now fixes 'trunk')" in proc.stderr
    assert "algo=grpo_lab" in proc.stderr and "import torchrl_grpo.experimental" in proc.stderr


def resume_and_train_on(run: str, run_dir: str) -> None:
    """Resume ``run``'s checkpoint, compare what was loaded with it, train one iteration."""
    path = DATA / f"v1_{run}.pt"
    ckpt = load_checkpoint(path)
    # The run's own keys come from its checkpoint (v1's algo.roots is the lab's today).
    overrides = [*TINY, f"resume={path}"]
    # One more iteration than the checkpoint's.
    cfg = compose_config([*overrides, f"experiment.total_frames={ckpt['frames'] + 1}"])
    trainer = Trainer(cfg, run_dir=run_dir)
    _assert_equal_state(ckpt["policy"], trainer.policy.state_dict())
    _assert_equal_state(ckpt["loss"], trainer.algo.loss.state_dict())
    _assert_equal_optimizer(ckpt["optimizer"], trainer.algo.optimizer.state_dict())
    if ckpt["value"] is not None:
        _assert_equal_state(ckpt["value"], trainer.algo.value.state_dict())
    assert (trainer.iteration, trainer.frames, trainer.algo.updates) == (
        ckpt["iteration"],
        ckpt["frames"],
        ckpt["updates"],
    )
    result = trainer.train()
    assert result.iterations == ckpt["iteration"] + 1 and result.frames > ckpt["frames"]
    new = load_checkpoint(result.checkpoint)
    # Version 1 still, with one key added since that its readers take as optional.
    assert new["version"] == ckpt["version"] and new.keys() == {*ckpt.keys(), "threads"}
    # The control: training went on from the loaded parameters.
    assert any(not torch.equal(v, new["policy"][k]) for k, v in ckpt["policy"].items())


@pytest.mark.parametrize(
    "run",
    # grpo_branch in the default suite; the other two (9 s each) with -m slow.
    [r if r == "grpo_branch" else pytest.param(r, marks=pytest.mark.slow) for r in sorted(RUNS)],
)
def test_an_old_checkpoint_resumes_bit_for_bit_and_trains_on(tmp_path, run):
    # In a fresh interpreter, as a user's: the checkpoint's queued roots hold simulator
    # states whose layout follows the vehicle classes registered in the process, and
    # other tests register some.
    code = (
        f"import sys; sys.path.insert(0, {str(HERE)!r}); "
        "from test_old_checkpoints import resume_and_train_on; "
        f"resume_and_train_on({run!r}, {str(tmp_path / run)!r})"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert proc.returncode == 0, proc.stderr[-3000:]


@pytest.mark.parametrize("run", ["grpo_continuation", "ppo"])
def test_an_old_checkpoint_evaluates_its_own_policy(tmp_path, run):
    path = DATA / f"v1_{run}.pt"
    cfg = compose_config(
        [f"checkpoint={path}", "episodes=2", "baselines=[slower]", "video=false"],
        config_name="evaluate",
    )
    report = evaluate_checkpoint(cfg, tmp_path)
    ckpt = load_checkpoint(path)
    trained = report.results[0]
    # v1's GRPO settings are not the recipe's: the run reads as an algo=grpo_lab run.
    name = typed_config(ckpt["config"]).algo.name
    assert trained.name == f"{name} ({ckpt['frames']} frames)"
    assert [r.name for r in report.results[1:]] == ["always-SLOWER"]
    # The same episodes driven by hand with the saved parameters.
    env_cfg = OmegaConf.create(ckpt["config"]["env"])
    env = make_env(env_cfg, seed=0)
    policy = make_policy(OmegaConf.create(ckpt["config"]["model"]), env)
    policy.load_state_dict(ckpt["policy"])
    # The final evaluation's seeds (20000 for configs older than the key).
    seed = typed_config(ckpt["config"]).experiment.final_eval_seed
    expected, _ = evaluate(env, policy, episodes=2, seed=seed, max_steps=env_cfg.max_episode_steps)
    assert (trained.returns, trained.seeds) == (expected.returns, expected.seeds)


def test_the_labs_defaults_are_the_old_schemas_so_a_migrated_run_reads_as_it_ran():
    from torchrl_grpo.experimental.grpo_lab import GRPOLabConfig, GRPOLabRolloutConfig
    from torchrl_grpo.training.retired_keys import OLD_DEFAULTS

    for schema, group in ((GRPOLabConfig, "algo"), (GRPOLabRolloutConfig, "rollout")):
        lab = to_container(
            OmegaConf.structured(schema(name="grpo_lab") if group == "algo" else schema)
        )
        old = OLD_DEFAULTS[group]
        assert {k: lab[k] for k in old} == old
