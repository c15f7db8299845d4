"""The experimental prior (``model=lab model.prior``): a network's logits plus a fixed bonus
on a scripted policy's action, built by ``make_policy`` through its policy wrapper."""

import pytest
import torch
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.experimental.grpo_lab import GRPOLabModelConfig
from torchrl_grpo.experimental.prior import PriorLogits
from torchrl_grpo.modules import (
    SCRIPTED_POLICIES,
    KinematicsLayout,
    KinematicsMLP,
    RulePolicy,
    make_scripted_policy,
)
from torchrl_grpo.modules.scripted.actions import SLOWER
from torchrl_grpo.training import compose_config
from torchrl_grpo.training.config_checks import check_config
from torchrl_grpo.training.model_builder import make_policy

pytestmark = pytest.mark.experimental


class _Fixed(nn.Module):
    """Returns the same logits for every input: a network whose output we know."""

    def __init__(self, logits: list[float]) -> None:
        super().__init__()
        self.logits = nn.Parameter(torch.tensor(logits))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.logits.expand(*observation.shape[:-2], -1)


def test_bonus_is_the_weight_on_the_prior_action_hand_computed():
    net = _Fixed([0.5, -1.0, 0.0, 2.0, 0.25])
    policy = PriorLogits(net, make_scripted_policy("slower"), 5, weight=3.0)
    out = policy(torch.zeros(2, 4, 5, 5))
    expected = torch.tensor([0.5, -1.0, 0.0, 2.0, 3.25]).expand(2, 4, 5)
    assert torch.equal(out, expected)


def test_the_prior_decides_per_observation():
    # RulePolicy's docstring scene: a slower car 10 m ahead and one beside, so it
    # brakes; alone on the road, it does something else.
    layout = KinematicsLayout()
    busy = torch.zeros(5, 5)
    busy[0] = torch.tensor([1.0, 0.5, 0.0, 25 / 80, 0.0])
    busy[1] = torch.tensor([1.0, 10 / 200, 0.0, -5 / 80, 0.0])
    busy[2] = torch.tensor([1.0, 0.0, 1 / 3, 0.0, 0.0])
    free = torch.zeros(5, 5)
    free[0] = busy[0]
    obs = torch.stack([busy, free])
    rule = RulePolicy(layout)
    actions = rule(TensorDict(observation=obs, batch_size=[2]))["action"]
    assert actions[0].item() == SLOWER and actions[1].item() != SLOWER
    policy = PriorLogits(_Fixed([0.0] * 5), rule, 5, weight=1.5)
    bonus = policy(obs)
    assert torch.equal(bonus, 1.5 * nn.functional.one_hot(actions, 5).float())


def test_only_the_network_is_trained():
    net = KinematicsMLP(5, 5, out_features=5, num_cells=(8,))
    policy = PriorLogits(net, make_scripted_policy("rule"), 5, weight=2.0)
    assert {n for n, _ in policy.named_parameters()} == {
        f"net.{n}" for n, _ in net.named_parameters()
    }
    policy(torch.randn(3, 5, 5)).sum().backward()
    assert all(p.grad is not None for p in net.parameters())


def test_bad_arguments_are_refused_naming_the_problem():
    with pytest.raises(ValueError, match="weight must be > 0, got 0.0"):
        PriorLogits(_Fixed([0.0] * 5), make_scripted_policy("slower"), 5, weight=0.0)
    with pytest.raises(ValueError, match="prior _Fixed has parameters"):
        PriorLogits(_Fixed([0.0] * 5), _Fixed([0.0] * 5), 5, weight=1.0)


def test_greedy_policy_with_a_large_weight_drives_as_the_prior():
    """A reference run: the scripted policy itself, on the same seeded episode."""
    cfg = OmegaConf.structured(GRPOLabModelConfig(num_cells=[16], prior="rule", prior_weight=50.0))
    env = HighwayEnv("highway-fast-v0", seed=3)
    actor = make_policy(cfg, env)
    assert isinstance(actor.module[0].module, PriorLogits)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        learned = env.rollout(15, actor, break_when_any_done=True)["action"]
    env = HighwayEnv("highway-fast-v0", seed=3)
    scripted = env.rollout(15, RulePolicy.from_highway_config(env.config))["action"]
    assert torch.equal(learned, scripted)
    assert len(set(scripted.tolist())) > 1  # the control: a non-constant action sequence


@pytest.mark.parametrize(
    "observation,problem",
    [
        ({"type": "Kinematics", "features": ["presence", "x"]}, "needed but not observed"),
        ({"type": "TimeToCollision"}, "no Kinematics observation"),
    ],
)
def test_make_policy_refuses_a_prior_it_cannot_read(observation, problem):
    cfg = OmegaConf.structured(GRPOLabModelConfig(prior="rule"))
    env = HighwayEnv("highway-fast-v0", config={"observation": observation}, seed=0)
    with pytest.raises(ValueError, match=f"model.prior=rule.*{problem}"):
        make_policy(cfg, env)


def test_a_prior_policy_is_typed_and_its_weight_positive():
    lab_run = ["experiment=smoke", "algo=grpo_lab", "model=lab"]
    cfg = compose_config([*lab_run, "model.prior=rule", "model.prior_weight=3"])
    check_config(cfg)
    assert cfg.model.prior == "rule" and cfg.model.prior_weight == 3.0
    with pytest.raises(ConfigCompositionException) as info:
        compose_config([*lab_run, "model.prior=rules"])
    assert "prior" in str(info.value.__cause__)
    cfg.model.prior_weight = 0.0
    with pytest.raises(ValueError, match="model.prior_weight must be > 0, got 0.0"):
        check_config(cfg)


def test_the_priors_are_scripted_policies():
    from torchrl_grpo.experimental.prior import PriorName

    assert {m.value for m in PriorName} < set(SCRIPTED_POLICIES)


def test_without_a_prior_the_policy_is_the_network():
    cfg = OmegaConf.structured(GRPOLabModelConfig(kind="mlp", num_cells=[8]))
    actor = make_policy(cfg, HighwayEnv("highway-fast-v0", seed=0))
    assert type(actor.module[0].module).__name__ == "KinematicsMLP"
