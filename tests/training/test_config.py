"""Every config group composes; typos and wrong types fail with the key's name."""

from __future__ import annotations

from typing import get_args

import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from train_setup import CONF, LAB_RUN, compose_config

from torchrl_grpo.experimental.grpo_lab import GRPOLabConfig
from torchrl_grpo.training import DistillConfig
from torchrl_grpo.training.algos.registry import with_fixed_settings
from torchrl_grpo.training.algos.search_distill import SearchDistillConfig
from torchrl_grpo.training.config import (
    GRPOConfig,
    PPOConfig,
    check_config,
    to_container,
)
from torchrl_grpo.training.resolvers import env_name

GROUPS = ["env", "model", "algo", "optim", "logger", "experiment"]


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize(
    "group,option", [(g, o) for g in GROUPS for o in _options(g)], ids=lambda x: str(x)
)
def test_every_group_option_composes(group, option):
    # The distillation has no default teachers: a path is enough to compose and check.
    teachers = ["algo.teachers=[runs/a/last.pt]"] if "distill" in option else []
    cfg = compose_config([f"{group}={option}", *teachers])
    check_config(cfg)
    assert OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves
    if group == "env":
        assert env_name(cfg.env.scenario) == option
    if group == "algo":
        assert str(cfg.algo.name) == option
        schemas = {
            "ppo": PPOConfig,
            "distill": DistillConfig,
            "search_distill": SearchDistillConfig,
            "grpo_lab": GRPOLabConfig,
        }
        schema = schemas.get(option, GRPOConfig)
        assert OmegaConf.get_type(cfg.algo) is schema


@pytest.mark.parametrize(
    ("overrides", "aversion"),
    [
        ([], 3.0),  # highway-fast-v0: the recipe's crash aversion
        (["env=merge"], 0.0),  # conf/model/scenario/merge_grpo_branch.yaml
        (["env=roundabout"], 3.0),  # its file keeps the recipe's aversion
        (["env=merge", "model.crash_aversion=2"], 2.0),  # the command line still wins
        (["env=merge", "model=mlp"], 0.0),  # for every network kind
    ],
)
def test_a_scenario_sets_its_own_defaults_under_the_command_line(overrides, aversion):
    cfg = compose_config(overrides)
    assert cfg.model.crash_head is True
    assert cfg.model.crash_aversion == aversion


@pytest.mark.parametrize(
    ("overrides", "margin"),
    [
        ([], None),
        (["env=roundabout"], 0.003),  # conf/model/scenario/roundabout_grpo_branch.yaml
        (["env=roundabout", "model.crash_margin=null"], None),
        (["env=roundabout", "model=scene"], 0.003),
    ],
)
def test_roundabout_bars_the_greedy_actions_riskier_than_slower(overrides, margin):
    assert compose_config(overrides).model.crash_margin == margin


@pytest.mark.parametrize(
    ("overrides", "kind"),
    [
        ([], "scene"),  # model=auto: the scenario's network
        (["env=roundabout"], "mlp"),
        (["env=merge"], "mlp"),  # SCENARIO_NETWORKS
        (["env=intersection"], "mlp"),
        (["env=merge", "algo=ppo"], "mlp"),  # the same network for the baseline
        (["env=merge", "model=scene"], "scene"),  # a chosen network wins
        (["env=merge", "model=ego_attention"], "ego_attention"),
    ],
)
def test_the_default_network_is_the_scenarios(overrides, kind):
    assert with_fixed_settings(compose_config(overrides)).model.kind == kind


def test_merge_alone_runs_the_recipe_measured_with_the_lab():
    # The command of docs/results.md, section 5, before its settings were merge's own.
    lab = [
        "env=merge",
        "model=mlp",
        "algo=grpo_lab",
        "rollout.horizon=30",
        "algo.tail_policy=slower",
        "algo.tail_learner_steps=0",
        "model.crash_aversion=0",
        "algo.group_fit_loss=regret",
        "algo.group_fit_coeff=1",
        "algo.replay_groups=32768",
        "experiment.total_frames=1200000",
    ]
    measured = OmegaConf.to_container(with_fixed_settings(compose_config(lab)))
    merge = OmegaConf.to_container(with_fixed_settings(compose_config(["env=merge"])))
    assert measured["algo"].pop("name") == "grpo_lab"
    assert merge["algo"].pop("name") == "grpo_branch"
    assert merge == measured
    assert merge["env"]["config"]["observation"]["features_range"]["x"] == [-400, 400]
    # Episode groups sample their actions: nothing to fit, and the config says so.
    with pytest.raises(ValueError, match="group_fit_loss=regret fits.*use algo=grpo_branch"):
        check_config(
            compose_config(["env=merge", "algo=grpo_episode", "algo.group_fit_loss=regret"])
        )
    # Its own settings give way to the command line's.
    cfg = compose_config(["env=merge", "rollout.horizon=8", "algo.group_fit_loss=regression"])
    assert (cfg.rollout.horizon, str(cfg.algo.group_fit_loss)) == (8, "regression")


def test_roundabout_alone_runs_the_recipe_measured_before_its_defaults():
    # The command of docs/results.md, section 5, that trained the runs the margin was
    # chosen on; the margin changes only the greedy choice.
    probe = [
        "env=roundabout",
        "model=mlp",
        "rollout.horizon=11",
        "algo.tail_policy=slower",
        "algo.tail_learner_steps=0",
        "algo.group_fit_loss=regret",
        "algo.replay_groups=32768",
        "experiment.total_frames=600000",
        "model.crash_margin=0.003",
    ]
    assert compose_config(probe) == compose_config(["env=roundabout"])
    # docs/results.md's override that undoes them gives the highway recipe's config.
    undone = "model=scene rollout.horizon=8 algo.tail_policy=rule algo.tail_learner_steps=7 "
    undone += "algo.group_fit_loss=regression algo.replay_groups=4096 model.crash_margin=null "
    highway = OmegaConf.to_container(
        compose_config(["env=highway_fast", "experiment.total_frames=600000"]), resolve=True
    )
    before = OmegaConf.to_container(
        compose_config(["env=roundabout", *undone.split()]), resolve=True
    )
    for group in ("model", "algo", "rollout", "experiment"):
        assert before[group] == highway[group], group


@pytest.mark.parametrize(
    ("overrides", "group_size", "tail_policy"),
    [
        ([], 5, "rule"),  # highway-fast-v0: the recipe's five meta-actions
        (["env=intersection"], 3, "idle"),  # conf/algo/scenario/intersection_grpo_branch.yaml
        (["env=intersection", "algo=grpo_lab"], 3, "idle"),
        (["env=intersection", "algo.tail_policy=slower"], 3, "slower"),  # the command line wins
    ],
)
def test_intersection_groups_enumerate_its_three_actions(overrides, group_size, tail_policy):
    cfg = compose_config(overrides)
    assert (cfg.algo.group_size, cfg.algo.tail_policy) == (group_size, tail_policy)


@pytest.mark.parametrize(
    "algo", ["grpo_branch", "grpo_episode", "ppo", "distill", "search_distill"]
)
def test_rollout_follows_the_algorithm(algo):
    cfg = compose_config([f"algo={algo}"])
    expected = OmegaConf.load(CONF / "rollout" / f"{algo}.yaml")
    assert cfg.rollout.num_workers == expected.num_workers
    if algo in ("ppo", "distill", "search_distill"):  # batches of steps: no group shape
        assert "horizon" not in cfg.rollout
        assert cfg.rollout.frames_per_batch == expected.frames_per_batch
    elif algo == "grpo_episode":
        assert cfg.rollout.horizon == cfg.env.max_episode_steps
    else:
        assert cfg.rollout.horizon == expected.horizon


def test_default_is_grpo_branch_on_highway_fast_with_offline_wandb():
    cfg = compose_config([])
    assert (cfg.env.scenario, str(cfg.algo.name), with_fixed_settings(cfg).algo.roots) == (
        "highway-fast-v0",
        "grpo_branch",
        "trunk",
    )
    assert str(cfg.logger.backend) == "wandb"  # offline; wandb_online streams


def test_issue_example_overrides_compose():
    cfg = compose_config(["env=merge", "algo.group_size=8", "logger=csv"])
    assert (cfg.env.scenario, cfg.algo.group_size, str(cfg.logger.backend)) == (
        "merge-v0",
        8,
        "csv",
    )


def test_evaluate_config_composes():
    cfg = compose_config(["checkpoint=x.pt", "env=merge"], config_name="evaluate")
    assert cfg.checkpoint == "x.pt" and cfg.env.scenario == "merge-v0" and cfg.episodes >= 30


@pytest.mark.parametrize("spelling", ["continue", "continuation"])
def test_roots_continue_keeps_its_older_spelling(spelling):
    cfg = compose_config(["algo=grpo_lab", f"algo.roots={spelling}"])
    assert str(cfg.algo.roots) == "continue"
    assert to_container(cfg)["algo"]["roots"] == "continue"  # what checkpoints now record
    with pytest.raises(ConfigCompositionException):
        compose_config(["algo=grpo_lab", "algo.roots=continues"])


def test_the_choices_are_the_librarys_literals():
    from torchrl_grpo.branching.branch_env import Backend as BranchBackend
    from torchrl_grpo.branching.continuation import Selection
    from torchrl_grpo.branching.group_collector import RootKind
    from torchrl_grpo.modules import SCRIPTED_POLICIES
    from torchrl_grpo.modules.greedy_tail import FirstAction
    from torchrl_grpo.modules.networks import NetworkKind
    from torchrl_grpo.objectives.bootstrap import BootstrapMode
    from torchrl_grpo.objectives.grpo_loss import Aggregation
    from torchrl_grpo.objectives.kl import KLEstimator
    from torchrl_grpo.training import choices as config
    from torchrl_grpo.training.algos.grpo_config import TailPolicyName
    from torchrl_grpo.training.model_builder import BasePolicyName

    for enum, literal in [
        (config.RootKindName, RootKind),
        (config.SelectionName, Selection),
        (config.AggregationName, Aggregation),
        (config.KLEstimatorName, KLEstimator),
        (config.BootstrapName, BootstrapMode),
        (config.FirstActionName, FirstAction),
    ]:
        assert [member.value for member in enum] == list(get_args(literal)), enum.__name__
    assert [m.value for m in config.Backend] == [*get_args(BranchBackend), "ray"]
    assert [m.value for m in config.ModelKind] == [*get_args(NetworkKind), "scene"]
    # The scripted base policies a greedy tail may name exist.
    assert set(get_args(BasePolicyName)) < set(SCRIPTED_POLICIES)
    assert {m.value for m in TailPolicyName} == {"learner", *get_args(BasePolicyName)}


def test_no_overrides_run_the_recommended_recipe():
    # The recipe as measured in docs/results.md (formerly `experiment=drive`).
    cfg = compose_config([])
    recipe = {
        "algo.name": "grpo_branch",
        "algo.tail_policy": "rule",
        "algo.tail_learner_steps": 7,
        "algo.replay_groups": 4096,
        "algo.group_fit_coeff": 1.0,
        "algo.group_fit_loss": "regression",
        "algo.group_fit_temperature": 1.0,
        "model.kind": "scene",
        "model.crash_head": True,
        "model.crash_aversion": 3.0,
        "rollout.stagger_trunks": True,
        "optim.anneal_lr": True,
        "optim.ema_decay": 0.995,
        "experiment.total_frames": 2_000_000,
    }
    run = with_fixed_settings(cfg)  # what the trainer executes
    assert {key: OmegaConf.select(run, key) for key in recipe} == recipe
    assert to_container(cfg) == to_container(compose_config(["experiment=drive"]))
    # algo=grpo_lab with no overrides is the same recipe, every setting a key.
    lab = with_fixed_settings(compose_config(["algo=grpo_lab"]))
    lab.algo.name = "grpo_branch"
    assert OmegaConf.to_container(lab) == OmegaConf.to_container(run)
    # Other algorithms keep the model group's own settings: no crash head.
    assert compose_config(["algo=ppo"]).model.crash_head is False


def _leaf_keys(node: dict, prefix: str = "") -> list[str]:
    out = []
    for key, value in node.items():
        if isinstance(value, dict) and value and key != "config":  # env.config: one key
            out += _leaf_keys(value, f"{prefix}{key}.")
        else:
            out.append(prefix + key)
    return out


@pytest.mark.parametrize(
    "overrides,count",
    [
        ([], 47),
        (["algo=grpo_episode"], 47),
        (["algo=ppo"], 43),
        (["algo=distill"], 44),
        (["experiment=search_student"], 49),
    ],
)
def test_a_run_composes_at_most_fifty_keys(overrides, count):
    keys = _leaf_keys(OmegaConf.to_container(compose_config(overrides)))
    assert len(keys) == count <= 50, sorted(keys)
    # Every core option of a group, over the default run or this one: at most 50 too.
    core = {"model": ["ego_attention", "mlp"], "rollout": ["ray"]}
    core["logger"] = ["wandb_online", "csv", "none"]
    for group, options in core.items():
        for option in options:
            if group == "rollout" and overrides:
                continue  # Ray collects GRPO-branch groups
            run = compose_config([*overrides, f"{group}={option}"])
            assert len(_leaf_keys(OmegaConf.to_container(run))) <= 50, (group, option)
    # The control: the experimental algorithm makes the fixed settings keys again.
    lab = _leaf_keys(OmegaConf.to_container(compose_config(LAB_RUN)))
    assert {"algo.roots", "rollout.live_trunks", "model.ensemble"} <= set(lab)
