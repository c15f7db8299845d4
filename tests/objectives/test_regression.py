"""AdvantageRegressionLoss against per-root squared errors computed by hand."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.objectives import AdvantageRegressionLoss
from torchrl_grpo.training.algos.enumerated import distill_targets


def _tabular_actor(table: torch.Tensor) -> ProbabilisticActor:
    return ProbabilisticActor(
        TensorDictModule(lambda state: table[state], ["state"], ["logits"]),
        ["logits"],
        distribution_class=torch.distributions.Categorical,
    )


def _groups(advantage: torch.Tensor) -> TensorDict:
    """One root per row of ``advantage`` ([roots, actions]), every action tried once."""
    roots, n = advantage.shape
    return TensorDict(
        state=torch.arange(roots).repeat_interleave(n),
        action=torch.arange(n).repeat(roots),
        advantage=advantage.reshape(-1, 1),
        group_id=torch.arange(roots).repeat_interleave(n) + 100,
        batch_size=[roots * n],
    )


@pytest.mark.parametrize("temperature", [0.1, 1.0, 4.0])
def test_whole_groups_give_the_mean_squared_error_of_each_roots_centred_logits(temperature):
    table = torch.nn.Parameter(torch.randn(4, 5))
    advantage = torch.randn(4, 5) * 3
    advantage -= advantage.mean(-1, keepdim=True)  # a group's advantages are centred
    data = distill_targets(_groups(advantage), temperature, "uniform", "regression")
    loss = AdvantageRegressionLoss(_tabular_actor(table), coeff=2.0, temperature=temperature)
    out = loss(data)
    centred = table.detach() - table.detach().mean(-1, keepdim=True)
    expected = (temperature * centred - advantage).pow(2).mean()
    torch.testing.assert_close(out["distill_squared_error"], expected)
    torch.testing.assert_close(out["loss_distill"].detach(), 2.0 * expected)
    out["loss_distill"].backward()
    # d/dl_a of mean over rows of (tau (l_a - mean l) - A_a)^2, through the centring.
    err = temperature * centred - advantage
    grad = 2.0 * 2 * temperature * (err - err.mean(-1, keepdim=True)) / err.numel()
    torch.testing.assert_close(table.grad, grad)


def test_the_minimum_is_the_softmax_of_the_advantages_over_the_temperature():
    advantage = torch.tensor([[-6.0, 1.0, 2.0, 2.0, 1.0]])
    table = torch.nn.Parameter(torch.zeros(1, 5))
    data = distill_targets(_groups(advantage), 0.5, "uniform", "regression")
    loss = AdvantageRegressionLoss(_tabular_actor(table), coeff=1.0, temperature=0.5)
    opt = torch.optim.Adam([table], lr=0.05)
    for _ in range(2000):
        opt.zero_grad()
        loss(data)["loss_distill"].backward()
        opt.step()
    probs = torch.softmax(table.detach(), -1)
    torch.testing.assert_close(probs, torch.softmax(advantage / 0.5, -1), atol=1e-4, rtol=0)


def test_the_targets_are_the_advantages_before_the_surrogates_reweighting():
    data = distill_targets(_groups(torch.tensor([[1.0, -1.0]])), 1.0, "uniform", "regression")
    data.set("advantage", data.get("advantage") * 3)  # what algo.action_weights=policy does
    torch.testing.assert_close(data.get("distill_target").squeeze(-1), torch.tensor([1.0, -1.0]))
    with pytest.raises(ValueError, match="loss must be 'cross_entropy' or 'regression'"):
        distill_targets(data, 1.0, "uniform", "huber")


def test_bad_arguments_and_inputs_are_named():
    actor = _tabular_actor(torch.zeros(1, 2))
    with pytest.raises(ValueError, match="temperature must be a finite number > 0"):
        AdvantageRegressionLoss(actor, coeff=1.0, temperature=0.0)
    with pytest.raises(ValueError, match="coeff must be a finite number > 0"):
        AdvantageRegressionLoss(actor, coeff=float("nan"), temperature=1.0)
    loss = AdvantageRegressionLoss(actor, coeff=1.0, temperature=1.0)
    data = TensorDict(
        state=torch.zeros(2, dtype=torch.long),
        action=torch.tensor([0, 1]),
        distill_target=torch.tensor([0.0, float("inf")]),
        distill_weight=torch.ones(2),
        batch_size=[2],
    )
    with pytest.raises(ValueError, match="distill_target"):
        loss(data)
    with pytest.raises(ValueError, match="no .distill_weight. entry"):
        loss(data.exclude("distill_weight"))
