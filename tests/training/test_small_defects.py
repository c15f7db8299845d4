"""Smaller defects a new user hit (issue 20, item 9): each refused or fixed, at start."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from train_setup import TINY, compose_config

from torchrl_grpo.training import Trainer
from torchrl_grpo.training.config import check_config


def test_episodes_of_zero_steps_are_refused_at_start(tmp_path):
    cfg = compose_config([*TINY, "env.max_episode_steps=0"])
    with pytest.raises(ValueError, match="env.max_episode_steps must be >= 1, got 0"):
        Trainer(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()  # nothing started, nothing written
    check_config(compose_config([*TINY, "env.max_episode_steps=1"]))


@pytest.mark.parametrize("where", [[], ["rollout=ray"]])
def test_replay_needs_a_scripted_tail_on_ray_as_locally(where):
    # Ray actors run the scripted tails: the recipe (rule tails, replay) is accepted there
    for tail in ("rule", "slower"):
        check_config(compose_config([*TINY, *where, f"algo.tail_policy={tail}"]))
    learner = ["algo.tail_policy=learner", "algo.tail_learner_steps=0"]
    cfg = compose_config([*TINY, *where, *learner, "algo.replay_groups=8"])
    with pytest.raises(ValueError, match="algo.replay_groups=8 replays old groups"):
        check_config(cfg)
    check_config(compose_config([*TINY, *where, *learner, "algo.replay_groups=null"]))


def test_recording_an_evaluation_prints_no_sdl_error(tmp_path):
    code = (
        "from omegaconf import OmegaConf\n"
        "from torchrl_grpo.modules import ConstantActionPolicy\n"
        "from torchrl_grpo.training import evaluate, make_env\n"
        "cfg = OmegaConf.create({'scenario': 'highway-fast-v0', 'config': {}})\n"
        "env, rec = make_env(cfg, seed=0), make_env(cfg, render_mode='rgb_array')\n"
        "for _ in range(2):\n"
        "    _, video = evaluate(env, ConstantActionPolicy('IDLE'), episodes=1, seed=0,\n"
        "                        max_steps=2, name='idle', record=rec)\n"
        "    assert video is not None and int(video.float().std()) > 0\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XDG_", "SDL_"))}
    proc = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "XDG_RUNTIME_DIR" not in proc.stdout + proc.stderr
