"""The experimental trunk clock (``algo=grpo_lab``: ``rollout.first_root_step``,
``rollout.full_horizon_roots``, ``algo.trunk=greedy``): its checks, its step ranges
worked by hand, and the greedy trunks' exploration type."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.experimental.grpo_lab import (
    GRPOLab,
    GRPOLabConfig,
    GRPOLabRolloutConfig,
)
from torchrl_grpo.experimental.trunk_clock import trunk_schedule
from torchrl_grpo.training import GRPO, Config
from torchrl_grpo.training.config_checks import check_config

pytestmark = pytest.mark.experimental


def test_the_trunks_bounds_need_trunks():
    for key in ("first_root_step", "full_horizon_roots"):
        rollout = GRPOLabRolloutConfig(**{key: 2 if key == "first_root_step" else True})
        cfg = OmegaConf.structured(
            Config(algo=GRPOLabConfig(name="grpo_lab", roots="reset"), rollout=rollout)
        )
        with pytest.raises(ValueError, match=f"rollout.{key}.*needs algo.roots=trunk"):
            check_config(cfg)
        cfg.algo.roots = "trunk"
        check_config(cfg)


def test_the_core_schedule_is_the_labs_without_bounds():
    rollout = OmegaConf.structured(GRPOLabRolloutConfig(horizon=8, stagger_trunks=True))
    assert GRPO.trunk_schedule(rollout, 30) == trunk_schedule(rollout, 30) == (30, 0, None)
    rollout.stagger_trunks = False
    assert GRPO.trunk_schedule(rollout, 30) == trunk_schedule(rollout, 30) == (0, 0, None)


def test_greedy_trunks_act_deterministically():
    algo = OmegaConf.structured(GRPOLabConfig(name="grpo_lab"))
    assert GRPOLab.trunk_exploration(algo) == GRPO.trunk_exploration(algo)
    assert GRPO.trunk_exploration(algo) == ExplorationType.RANDOM
    algo.trunk = "greedy"
    assert GRPOLab.trunk_exploration(algo) == ExplorationType.DETERMINISTIC


def test_the_trunk_schedule_names_an_empty_step_range():
    rollout = OmegaConf.structured(GRPOLabRolloutConfig(horizon=8, full_horizon_roots=True))
    assert trunk_schedule(rollout, 30) == (0, 0, 23)
    rollout.stagger_trunks, rollout.first_root_step = True, 22
    assert trunk_schedule(rollout, 30) == (1, 22, 23)
    rollout.first_root_step = 23
    with pytest.raises(ValueError, match="rollout.first_root_step=23 leaves no decision point"):
        trunk_schedule(rollout, 30)
    rollout.first_root_step, rollout.horizon = 0, 31
    with pytest.raises(ValueError, match="rollout.horizon=31"):
        trunk_schedule(rollout, 30)
