"""The experimental lagging tail policy (``algo=grpo_lab algo.tail_sync_batches=k``): its
checks, its refresh every k batches, and its exact resume."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))

from train_helpers import LAB, train_run  # noqa: E402
from train_setup import TINY, compose_config  # noqa: E402

from torchrl_grpo.experimental.grpo_lab import GRPOLabConfig  # noqa: E402
from torchrl_grpo.training import Config, Trainer  # noqa: E402
from torchrl_grpo.training.config_checks import check_config  # noqa: E402

pytestmark = pytest.mark.experimental


def test_a_lagging_tail_is_the_learners_and_follows_greedy_tails():
    cfg = OmegaConf.structured(
        Config(algo=GRPOLabConfig(name="grpo_lab", explore_steps=1, tail_policy="slower"))
    )
    check_config(cfg)
    cfg.algo.tail_sync_batches = 2
    with pytest.raises(ValueError, match="algo.tail_sync_batches null"):
        check_config(cfg)
    cfg.algo.tail_policy = "learner"
    check_config(cfg)
    cfg.algo.tail_sync_batches = 0
    with pytest.raises(ValueError, match="algo.tail_sync_batches=0: must be >= 1"):
        check_config(cfg)
    cfg.algo.tail_sync_batches, cfg.algo.explore_steps = 2, None
    with pytest.raises(ValueError, match="applies to greedy-tail branches only"):
        check_config(cfg)


def test_resume_restores_the_lagging_tail_policy(tmp_path):
    common = [
        *LAB,
        "algo.group_size=5",
        "rollout.horizon=2",
        "algo.explore_steps=1",
        "algo.first_action=enumerate",
        "algo.trunk=greedy",
        "algo.tail_sync_batches=2",
        "algo.tail_policy=learner",
        "algo.tail_learner_steps=0",
        "algo.replay_groups=null",
    ]
    stopped = train_run(tmp_path, "stopped", [*common, "experiment.total_frames=70"])
    assert stopped.iteration == 3
    tail, policy = stopped.algo.tail_policy.state_dict(), stopped.policy.state_dict()
    assert any(not torch.equal(tail[k], policy[k]) for k in tail)  # it lags one batch
    cfg = compose_config(
        [
            *TINY,
            *common,
            "experiment.total_frames=130",
            f"resume={tmp_path / 'stopped' / 'last.pt'}",
        ]
    )
    resumed = Trainer(cfg, run_dir=tmp_path / "resumed").algo.tail_policy.state_dict()
    for key, value in tail.items():
        assert torch.equal(resumed[key], value), key
