"""Config checks: typos, wrong types and settings that cannot go together fail naming the key."""

from __future__ import annotations

import shutil

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError
from train_setup import CONF, LAB, LAB_RUN, compose_config

from torchrl_grpo.experimental.grpo_lab import GRPOLabRolloutConfig
from torchrl_grpo.training.algos.registry import with_fixed_settings
from torchrl_grpo.training.config import (
    Config,
    GRPOConfig,
    check_config,
)
from torchrl_grpo.training.group_schemas import GroupRolloutConfig, RayRolloutConfig


@pytest.mark.parametrize(
    "override,key",
    [
        ("algo.clip_epsilon=0.3", "algo.clip_epsilon"),  # a PPO key on a GRPO algo
        ("optim.lrr=1e-3", "optim.lrr"),
        ("experiment.total_frame=10", "experiment.total_frame"),
    ],
)
def test_misspelt_key_fails_naming_it(override, key):
    with pytest.raises(ConfigCompositionException, match=key.replace(".", r"\.")):
        compose_config([override])


@pytest.mark.parametrize(
    "override,key",
    [
        ("algo.group_size=eight", "group_size"),
        ("algo.tail_policy=rules", "tail_policy"),
        ("model.kind=lstm", "kind"),
        ("logger=csv", None),
    ],
)
def test_wrong_type_or_choice_fails_naming_the_key(override, key):
    if key is None:  # the control: a valid override composes
        compose_config([override])
        return
    with pytest.raises(ConfigCompositionException) as info:
        compose_config([override])
    cause = info.value.__cause__
    assert isinstance(cause, ValidationError)
    assert key in str(cause)


def test_typo_inside_a_yaml_file_fails_at_load(tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(CONF, conf)
    path = conf / "algo" / "grpo_branch.yaml"
    path.write_text(path.read_text().replace("group_size: 5", "grup_size: 5"))
    with pytest.raises(ConfigCompositionException, match="grup_size") as info:
        compose_config([], conf=conf)
    assert "algo.grup_size" in str(info.value)


def test_check_config_names_the_key():
    cfg = OmegaConf.structured(Config(rollout=GroupRolloutConfig(num_workers=2)))
    with pytest.raises(ValueError, match="rollout.num_workers"):
        check_config(cfg)
    cfg = OmegaConf.structured(Config(algo=GRPOConfig(name="grpo_branch", group_size=1)))
    with pytest.raises(ValueError, match="algo.group_size"):
        check_config(cfg)
    cfg = OmegaConf.structured(Config(algo=LAB(first_action="enumerate")))
    with pytest.raises(ValueError, match="algo.explore_steps"):
        check_config(cfg)
    cfg.algo.explore_steps = 1
    check_config(cfg)


def test_learner_steps_need_a_scripted_tail():
    cfg = OmegaConf.structured(Config(algo=LAB(explore_steps=1, tail_learner_steps=2)))
    with pytest.raises(ValueError, match="algo.tail_learner_steps=2.*scripted algo.tail_policy"):
        check_config(cfg)
    cfg.algo.tail_policy = "rule"
    check_config(cfg)
    cfg.algo.tail_learner_steps = -1
    with pytest.raises(ValueError, match="algo.tail_learner_steps=-1: must be >= 0"):
        check_config(cfg)


def test_a_scripted_tail_needs_greedy_tail_branches():
    cfg = OmegaConf.structured(Config(algo=LAB(tail_policy="slower")))
    with pytest.raises(ValueError, match="algo.tail_policy=slower.*algo.explore_steps"):
        check_config(cfg)
    cfg.algo.explore_steps = 1
    check_config(cfg)
    with pytest.raises(ValidationError, match="tail_policy"):
        cfg.algo.tail_policy = "slowr"
    on_ray = OmegaConf.structured(
        Config(
            algo=LAB(explore_steps=1, tail_policy="slower"),
            rollout=RayRolloutConfig(),
        )
    )
    check_config(on_ray)  # Ray actors run the scripted tails too
    on_ray.algo.explore_steps = None
    with pytest.raises(ValueError, match="algo.tail_policy=slower.*algo.explore_steps"):
        check_config(on_ray)


def test_replay_needs_policy_independent_advantages():
    cfg = OmegaConf.structured(Config(algo=LAB(explore_steps=1, replay_groups=10)))
    with pytest.raises(ValueError, match="algo.first_action=enumerate and a scripted"):
        check_config(cfg)
    cfg.algo.first_action = "enumerate"
    with pytest.raises(ValueError, match="algo.tail_policy"):
        check_config(cfg)  # the learner's own tail: advantages change with the policy
    cfg.algo.tail_policy = "rule"
    check_config(cfg)
    cfg.algo.replay_groups = 0
    with pytest.raises(ValueError, match="algo.replay_groups must be >= 1"):
        check_config(cfg)


def test_staggered_trunks_need_live_trunks():
    cfg = OmegaConf.structured(
        Config(algo=LAB(), rollout=GRPOLabRolloutConfig(stagger_trunks=True))
    )
    with pytest.raises(ValueError, match="rollout.stagger_trunks=true.*rollout.live_trunks=true"):
        check_config(cfg)
    cfg.rollout.live_trunks = True
    check_config(cfg)


def test_a_null_sync_keeps_the_reference_frozen():
    from torchrl_grpo.envs import HighwayEnv
    from torchrl_grpo.training.loss_builder import make_loss, make_reference_sync
    from torchrl_grpo.training.model_builder import make_policy

    cfg = compose_config([*LAB_RUN, "algo.ref_model_sync_steps=null", "algo.kl_to_ref_coeff=0.01"])
    loss = make_loss(cfg.algo, make_policy(cfg.model, HighwayEnv(seed=0)), None)
    assert make_reference_sync(cfg.algo, loss) is None
    cfg = compose_config(["algo.kl_to_ref_coeff=0.01"])  # the control: syncs every 64 updates
    assert make_reference_sync(with_fixed_settings(cfg).algo, loss) is not None


def test_policy_action_weights_need_enumerated_actions():
    cfg = OmegaConf.structured(Config(algo=LAB(explore_steps=1, action_weights="policy")))
    with pytest.raises(ValueError, match="algo.action_weights=policy.*first_action=enumerate"):
        check_config(cfg)
    cfg.algo.first_action = "enumerate"
    check_config(cfg)


def test_distillation_needs_one_roots_enumerated_actions():
    cfg = OmegaConf.structured(Config(algo=LAB(explore_steps=1, group_fit_coeff=1.0)))
    with pytest.raises(
        ValueError, match="algo.group_fit_coeff=1.0 distils.*first_action=enumerate"
    ):
        check_config(cfg)
    cfg.algo.first_action = "enumerate"
    check_config(cfg)
    cfg.algo.explore_steps = 2  # rows of a group at step 1 are not one state's actions
    with pytest.raises(ValueError, match="explore_steps=1"):
        check_config(cfg)
    cfg.algo.explore_steps = 1
    cfg.algo.group_fit_temperature = -0.5
    with pytest.raises(ValueError, match="algo.group_fit_temperature must be a finite number >= 0"):
        check_config(cfg)
    cfg.algo.group_fit_temperature = 0.0
    cfg.algo.group_fit_loss = "regression"  # logits read as advantages / temperature
    with pytest.raises(ValueError, match="group_fit_loss=regression.*temperature > 0"):
        check_config(cfg)
    cfg.algo.group_fit_loss = "cross_entropy"
    cfg.algo.group_fit_coeff = -1.0
    with pytest.raises(ValueError, match="algo.group_fit_coeff must be a finite number >= 0"):
        check_config(cfg)


@pytest.mark.parametrize("option", ["algo.bootstrap=survival", "algo.crash_label=bootstrap"])
def test_a_survival_bootstrap_needs_a_crash_head(option):
    cfg = compose_config([*LAB_RUN, option, "model.crash_head=false"])
    with pytest.raises(ValueError, match=f"{option}.*model.crash_head=true"):
        check_config(cfg)
    cfg.model.crash_head = True
    check_config(cfg)


def test_the_crash_label_is_a_checked_choice():
    with pytest.raises(Exception, match="crash_label"):
        compose_config([*LAB_RUN, "algo.crash_label=episode"])
