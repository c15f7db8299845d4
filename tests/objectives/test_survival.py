"""TailSurvival and the survival bootstrap against hand-computed probabilities and tails."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from test_bootstrap import LAST, TAILS, _batch
from torch import nn

from torchrl_grpo.modules import CrashHead
from torchrl_grpo.objectives import HorizonBootstrap
from torchrl_grpo.objectives.survival import TailSurvival, crash_label


class StepHead(nn.Module):
    """A head whose observation is ``[step]``: it prefers action ``step % 2``.

    Action ``a``'s crash logit at step ``t`` is ``t - a``, so the greedy action's crash
    probability is ``sigmoid(t - t % 2)``.
    """

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        step = observation[..., 0]
        return torch.stack([(step % 2 == 0).float(), (step % 2 == 1).float()], -1)

    def crash_logits(self, observation: torch.Tensor) -> torch.Tensor:
        step = observation[..., :1]
        return step - torch.arange(2.0)


def _observed(batch: TensorDict) -> TensorDict:
    # The observation after step t is [t], for the 3 branches of 4 steps.
    steps = torch.arange(4.0).expand(1, 3, 4).unsqueeze(-1)
    return batch.set(("next", "observation"), steps.clone())


def _sigmoid(x: float) -> float:
    return 1 / (1 + math.exp(-x))


def test_survival_is_read_at_each_branchs_last_step_for_the_greedy_action():
    out = TailSurvival(StepHead())(_observed(_batch()))
    # Last steps 3, 1, 2: greedy actions 1, 1, 0; crash logits 3 - 1, 1 - 1, 2 - 0.
    expected = [1 - _sigmoid(2.0), 1 - _sigmoid(0.0), 1 - _sigmoid(2.0)]
    assert LAST == [3, 1, 2]
    survival = out["tail_survival"]
    assert survival.shape == (1, 3, 4)
    torch.testing.assert_close(survival[0, :, 0], torch.tensor(expected))
    # The same value on every step of a branch.
    assert bool((survival == survival[..., :1]).all())


def test_a_branch_without_a_valid_step_survives_and_keys_can_be_renamed():
    batch = _observed(_batch())
    batch["mask"][0, 1] = False
    batch = batch.rename_key_(("next", "observation"), "obs")
    module = TailSurvival(StepHead()).set_keys(observation="obs", survival="p")
    assert module.in_keys == ["obs", "mask"] and module.out_keys == ["p"]
    assert float(module(batch)["p"][0, 1, 0]) == 1.0
    with pytest.raises(ValueError, match="not accepted keys"):
        module.set_keys(obs="x")
    with pytest.raises(TypeError, match="crash_logits.*model.crash_head=true"):
        TailSurvival(nn.Linear(1, 2))


def test_the_survival_bootstrap_scales_each_tail_by_its_branchs_survival():
    batch = _batch()
    survival = torch.tensor([0.5, 0.25, 0.8]).reshape(1, 3, 1).expand(1, 3, 4).clone()
    batch["tail_survival"] = survival
    out = HorizonBootstrap(step_limit=30, mode="survival")(batch)
    expected = [tail * p for tail, p in zip(TAILS, [0.5, 0.25, 0.8], strict=True)]
    tails = out["bootstrap"].reshape(3, 4).sum(-1)
    torch.testing.assert_close(tails, torch.tensor(expected))
    # The crashed branch (1) gets no tail whatever its survival; the others' rewards
    # are the env's plus the scaled tail at their last step.
    assert float(tails[1]) == 0.0
    plain = HorizonBootstrap(step_limit=30)(_batch())
    torch.testing.assert_close(
        out["next", "train_reward"] - out["bootstrap"],
        plain["next", "train_reward"] - plain["bootstrap"],
    )


def test_the_survival_bootstrap_refuses_a_missing_or_improper_survival():
    module = HorizonBootstrap(step_limit=30, mode="survival")
    assert module.in_keys[-1] == "tail_survival"
    with pytest.raises(KeyError, match="'tail_survival'.*TailSurvival"):
        module(_batch())
    batch = _batch()
    batch["tail_survival"] = torch.full((1, 3, 4), 1.5)
    with pytest.raises(ValueError, match="probabilities in \\[0, 1\\]"):
        module(batch)


def test_survival_from_a_crash_head_network_feeds_the_bootstrap():
    net = nn.Linear(1, 4)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(torch.tensor([0.0, 2.0, math.log(3), 0.0]))  # prefers action 1
    batch = TailSurvival(CrashHead(net, 2))(_observed(_batch()))
    out = HorizonBootstrap(step_limit=30, mode="survival")(batch)
    # Action 1's crash logit 0: every tail is halved.
    torch.testing.assert_close(out["bootstrap"].reshape(3, 4).sum(-1), torch.tensor(TAILS) * 0.5)


def test_the_bootstrapped_crash_label_is_one_the_heads_estimate_or_zero():
    crashed = torch.tensor([True, True, False, False])
    cut = torch.tensor([False, True, True, False])
    survival = torch.tensor([0.9, 0.2, 0.75, 0.5])
    # A crash is 1 whatever the head says; a cut branch is the head's 1 - survival; a
    # branch whose episode ended alive is 0.
    assert crash_label(crashed, cut, survival).tolist() == [1.0, 1.0, 0.25, 0.0]
    # Broadcast: one survival per branch against a [branches, steps] mask.
    out = crash_label(crashed[:, None].expand(4, 3), cut[:, None], survival[:, None])
    assert out.shape == (4, 3) and out[:, 0].tolist() == [1.0, 1.0, 0.25, 0.0]
    assert crash_label(crashed, cut, survival.double()).dtype == torch.float64
