"""The experimental cross-entropy group fit (``algo=grpo_lab algo.group_fit_loss=cross_entropy``):
GroupDistillLoss and its per-root targets, against per-group softmaxes and autograd, and the
spread weighting of roots (``algo.group_fit_weighting=spread``)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.experimental.group_distill import (
    GroupDistillLoss,
    group_softmax_target,
    group_spread,
)
from torchrl_grpo.objectives import AdvantageRegressionLoss
from torchrl_grpo.training.algos.enumerated import distill_targets

pytestmark = pytest.mark.experimental


def _tabular_actor(table: torch.Tensor) -> ProbabilisticActor:
    return ProbabilisticActor(
        TensorDictModule(lambda state: table[state], ["state"], ["logits"]),
        ["logits"],
        distribution_class=torch.distributions.Categorical,
    )


@pytest.mark.parametrize("temperature", [0.05, 0.5, 3.0])
def test_targets_are_each_groups_softmax_in_any_row_order(temperature):
    n_groups, n_actions = 7, 5
    advantage = torch.randn(n_groups, n_actions) * 2
    expected = torch.softmax(advantage / temperature, -1)
    # Shuffled rows, sparse group ids: the grouping comes from the ids only.
    ids = torch.tensor([3, 90, 11, 4, 57, 8, 1000]).repeat_interleave(n_actions)
    perm = torch.randperm(n_groups * n_actions)
    weight = group_softmax_target(advantage.reshape(-1, 1)[perm], ids[perm], temperature)
    assert weight.shape == (n_groups * n_actions, 1)
    restored = torch.empty_like(weight).index_copy_(0, perm, weight).reshape(n_groups, n_actions)
    torch.testing.assert_close(restored, expected)


def test_spreads_are_each_groups_best_minus_worst_in_any_row_order():
    n_groups, n_actions = 6, 5
    advantage = torch.randn(n_groups, n_actions) * 3
    advantage[2] = 1.5  # a tie: nothing to teach
    expected = (advantage.max(-1).values - advantage.min(-1).values).repeat_interleave(n_actions)
    ids = torch.tensor([7, 0, 42, 5, 300, 2]).repeat_interleave(n_actions)
    perm = torch.randperm(n_groups * n_actions)
    spread = group_spread(advantage.reshape(-1, 1)[perm], ids[perm])
    assert spread.shape == (n_groups * n_actions, 1)
    torch.testing.assert_close(spread.squeeze(-1), expected[perm])
    assert bool((spread.squeeze(-1)[ids[perm] == 42] == 0).all())
    with pytest.raises(ValueError, match="one value per row: 4 values"):
        group_spread(torch.zeros(4), torch.zeros(3))


def test_spread_weighting_counts_each_root_by_its_spread_in_the_loss():
    """The loss is ``sum_s spread(s) CE(s) / sum_s spread(s)``: hand-made groups."""
    table = torch.nn.Parameter(torch.randn(3, 5))
    # Root 0 spread 10 (a crash), root 1 spread 1, root 2 a tie (spread 0).
    advantage = torch.tensor(
        [[-8.0, 2.0, 2.0, 2.0, 2.0], [0.0, 1.0, 0.5, 0.5, 0.5], [0.3, 0.3, 0.3, 0.3, 0.3]]
    )
    data = TensorDict(
        state=torch.arange(3).repeat_interleave(5),
        action=torch.arange(5).repeat(3),
        advantage=advantage.reshape(-1, 1),
        group_id=torch.arange(3).repeat_interleave(5) + 10,
        batch_size=[15],
    )
    data = distill_targets(data, 0.0, "spread", "cross_entropy")
    loss = GroupDistillLoss(_tabular_actor(table), coeff=1.0)(data)["loss_distill"]
    logp = torch.log_softmax(table.detach(), -1)
    ce0 = -logp[0, 1:].mean()  # four best actions share the hard target
    ce1 = -logp[1, 1]
    torch.testing.assert_close(loss.detach(), (10 * ce0 + 1 * ce1) / 11)
    with pytest.raises(ValueError, match="weighting must be 'uniform' or 'spread'"):
        distill_targets(data, 0.0, "crash")


def test_a_zero_temperature_splits_the_weight_over_the_best_actions():
    advantage = torch.tensor([1.0, 3.0, 3.0, 0.0, -5.0, -5.0, -5.0])
    groups = torch.tensor([0, 0, 0, 0, 1, 1, 1])
    third = 1 / 3
    expected = torch.tensor([0.0, 0.5, 0.5, 0.0, third, third, third])
    torch.testing.assert_close(group_softmax_target(advantage, groups, 0.0), expected)
    # Huge gaps do not overflow: the softmax is shifted by each group's best.
    far = group_softmax_target(torch.tensor([1e4, 0.0]), torch.tensor([0, 0]), 1e-3)
    assert far.tolist() == [1.0, 0.0]


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf")])
def test_a_bad_temperature_is_refused(bad):
    with pytest.raises(ValueError, match="temperature must be a finite number >= 0"):
        group_softmax_target(torch.zeros(2), torch.zeros(2), bad)


def test_one_advantage_per_group_id():
    with pytest.raises(ValueError, match="4 values .advantages. for 2 group ids"):
        group_softmax_target(torch.zeros(2, 2), torch.zeros(2), 1.0)


def test_the_loss_is_the_cross_entropy_to_each_roots_target_and_its_gradient():
    """Against autograd of ``-sum_s sum_a q(a|s) log pi(a|s) / n_states``."""
    n_states, n_actions, coeff = 4, 5, 0.7
    table = torch.nn.Parameter(torch.randn(n_states, n_actions))
    advantage = torch.randn(n_states, n_actions)
    target = torch.softmax(advantage / 0.3, -1)
    data = TensorDict(
        state=torch.arange(n_states).repeat_interleave(n_actions),
        action=torch.arange(n_actions).repeat(n_states),
        distill_weight=group_softmax_target(
            advantage.reshape(-1), torch.arange(n_states).repeat_interleave(n_actions), 0.3
        ),
        batch_size=[n_states * n_actions],
    )
    out = GroupDistillLoss(_tabular_actor(table), coeff=coeff)(data)
    out["loss_distill"].backward()
    reference = table.detach().clone().requires_grad_(True)
    cross_entropy = -(target * torch.log_softmax(reference, -1)).sum(-1).mean()
    (coeff * cross_entropy).backward()
    torch.testing.assert_close(out["loss_distill"].detach(), coeff * cross_entropy.detach())
    torch.testing.assert_close(out["distill_cross_entropy"], cross_entropy.detach())
    torch.testing.assert_close(table.grad, reference.grad)


def test_a_step_on_the_loss_moves_the_policy_to_the_best_action():
    table = torch.nn.Parameter(torch.zeros(1, 3))
    data = TensorDict(
        state=torch.zeros(3, dtype=torch.long),
        action=torch.arange(3),
        distill_weight=group_softmax_target(torch.tensor([0.0, 2.0, -9.0]), torch.zeros(3), 0.0),
        batch_size=[3],
    )
    loss = GroupDistillLoss(_tabular_actor(table), coeff=1.0)
    optimizer = torch.optim.SGD([table], lr=1.0)
    for _ in range(20):
        optimizer.zero_grad()
        loss(data)["loss_distill"].backward()
        optimizer.step()
    assert torch.softmax(table.detach(), -1)[0, 1] > 0.9


def test_bad_inputs_are_refused_naming_them():
    actor = _tabular_actor(torch.nn.Parameter(torch.zeros(1, 2)))
    for coeff in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="coeff must be a finite number > 0"):
            GroupDistillLoss(actor, coeff=coeff)
    loss = GroupDistillLoss(actor, coeff=1.0)
    rows = {"state": torch.zeros(2, dtype=torch.long), "action": torch.arange(2)}
    with pytest.raises(ValueError, match="no .distill_weight. entry"):
        loss(TensorDict(rows, batch_size=[2]))
    # Rows that are none of their groups' best: no pull, no error.
    out = loss(TensorDict({**rows, "distill_weight": torch.zeros(2)}, batch_size=[2]))
    assert float(out["loss_distill"]) == 0.0
    with pytest.raises(ValueError, match="'distill_weight'"):
        nan = torch.tensor([1.0, float("nan")])
        loss(TensorDict({**rows, "distill_weight": nan}, batch_size=[2]))
    loss.set_keys(target_weight="q")
    out = loss(TensorDict({**rows, "q": torch.tensor([1.0, 0.0])}, batch_size=[2]))
    assert float(out["distill_cross_entropy"]) == pytest.approx(0.6931, abs=1e-4)


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


def test_spread_weights_count_each_root_by_its_spread():
    table = torch.nn.Parameter(torch.randn(3, 5))
    advantage = torch.tensor(
        [[-8.0, 2.0, 2.0, 2.0, 2.0], [-0.5, 0.5, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0]]
    )
    data = distill_targets(_groups(advantage), 1.0, "spread", "regression")
    out = AdvantageRegressionLoss(_tabular_actor(table), coeff=1.0, temperature=1.0)(data)
    centred = table.detach() - table.detach().mean(-1, keepdim=True)
    per_root = (centred - advantage).pow(2).sum(-1)
    # Spreads 10, 1 and 0 (a tie teaches nothing); each root's 5 rows carry its spread.
    expected = (10 * per_root[0] + 1 * per_root[1]) / (5 * 11)
    torch.testing.assert_close(out["distill_squared_error"], expected)
