"""The expected-regret group fit: its per-root targets and its loss, against hand computations."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.objectives import GroupRegretLoss
from torchrl_grpo.objectives.group_targets import group_best_set, group_reduce, group_regret
from torchrl_grpo.objectives.regret_fit import ANCHOR
from torchrl_grpo.training.algos.enumerated import GROUP_FITS, distill_targets


def _shuffled_groups(n_groups: int = 7, size: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    # Ties on purpose (rounded advantages), ids neither dense nor sorted, rows shuffled.
    advantage = torch.randn(n_groups * size).mul(2).round()
    ids = torch.arange(n_groups).mul(13).add(4).repeat_interleave(size)
    perm = torch.randperm(ids.numel())
    return advantage[perm], ids[perm]


def test_the_targets_match_a_loop_over_each_group():
    advantage, ids = _shuffled_groups()
    regret, best = group_regret(advantage, ids), group_best_set(advantage, ids)
    spread = group_reduce(advantage, ids, "amax") - group_reduce(advantage, ids, "amin")
    for gid in ids.unique():
        rows = ids == gid
        values = advantage[rows].tolist()
        top = max(values)
        assert regret[rows].tolist() == [top - v for v in values]
        n_best = values.count(top)
        assert best[rows].tolist() == pytest.approx([(v == top) / n_best for v in values])
        assert spread[rows].tolist() == [top - min(values)] * len(values)
    # [N, 1] in, [N, 1] out, as advantages are stored.
    assert group_regret(advantage[:, None], ids).shape == (ids.numel(), 1)


def test_the_targets_name_bad_input():
    with pytest.raises(ValueError, match="one value per row: 4 values .advantages. for 3 group"):
        group_regret(torch.zeros(4), torch.zeros(3))
    with pytest.raises(ValueError, match="reduce must be one of.*'mean'"):
        group_reduce(torch.zeros(2), torch.zeros(2), "mean")


def _actor(logits: torch.Tensor) -> ProbabilisticActor:
    # A row's observation is its state's index: the logits of that state, learnable.
    table = torch.nn.Embedding.from_pretrained(logits.clone(), freeze=False)
    net = TensorDictModule(lambda s: table(s.squeeze(-1)), ["observation"], ["logits"])
    actor = ProbabilisticActor(net, ["logits"], distribution_class=torch.distributions.Categorical)
    actor.table = table
    return actor


def test_the_loss_is_the_expected_regret_plus_the_anchor_by_hand():
    # Two roots of three actions; the second has two best actions.
    logits = torch.tensor([[0.0, 1.0, 2.0], [1.0, 0.0, 1.0]])
    advantage = torch.tensor([1.0, -2.0, 1.0, 3.0, 0.0, 3.0])
    ids = torch.tensor([0, 0, 0, 1, 1, 1])
    data = TensorDict(
        observation=torch.tensor([[0], [0], [0], [1], [1], [1]]),
        action=torch.tensor([0, 1, 2, 0, 1, 2]),
        advantage=advantage[:, None],
        group_id=ids,
        batch_size=[6],
    )
    data = distill_targets(data, 0.0, loss="regret")
    out = GroupRegretLoss(_actor(logits), coeff=2.0)(data)
    p = logits.softmax(-1)
    expected = ((p[0] * torch.tensor([0.0, 3.0, 0.0])).sum() + p[1, 1] * 3.0) / 2
    # Each root's best set shares its weight: actions 0 and 2 of both roots, 1/2 each.
    best = p[[0, 0, 1, 1], [0, 2, 0, 2]]
    anchor = -(0.5 * best.log()).sum() / 2
    torch.testing.assert_close(out["distill_expected_regret"], expected)
    torch.testing.assert_close(out["loss_distill"], 2.0 * (expected + ANCHOR * anchor))


def _fitted_probability_of_action_0(loss_name: str) -> float:
    """Two roots the policy cannot tell apart (the same observation), actions 0 and 1
    tried from each. At the first, action 1 loses 10; at the second, action 0 loses 1."""
    data = TensorDict(
        observation=torch.zeros(4, 1, dtype=torch.long),
        action=torch.tensor([0, 1, 0, 1]),
        advantage=torch.tensor([[5.0], [-5.0], [-0.5], [0.5]]),
        group_id=torch.tensor([0, 0, 1, 1]),
        batch_size=[4],
    )
    data = distill_targets(data, 0.0, loss=loss_name)
    actor = _actor(torch.zeros(1, 2))
    loss = GROUP_FITS[loss_name].make_loss(actor, 1.0, 0.0)
    optim = torch.optim.Adam(actor.parameters(), lr=0.05)
    for _ in range(300):
        optim.zero_grad()
        loss(data)["loss_distill"].backward()
        optim.step()
    with torch.no_grad():
        return float(actor.get_dist(data[:1]).probs[0, 0])


def test_the_fit_plays_the_action_that_costs_less_where_roots_look_alike():
    # Regrets: action 0 costs 0 and 1 (mean 0.5), action 1 costs 10 and 0 (mean 5).
    assert _fitted_probability_of_action_0("regret") > 0.9


def test_bad_input_is_named():
    actor = _actor(torch.zeros(1, 2))
    for coeff in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="coeff must be a finite number > 0"):
            GroupRegretLoss(actor, coeff=coeff)
    data = TensorDict(
        observation=torch.zeros(2, 1, dtype=torch.long),
        action=torch.tensor([0, 1]),
        distill_weight=torch.tensor([1.0, 0.0]),
        batch_size=[2],
    )
    loss = GroupRegretLoss(actor, coeff=1.0)
    with pytest.raises(ValueError, match=r"no 'distill_target' entry.*set_keys\(regret="):
        loss(data)
    data["distill_target"] = torch.tensor([0.0, float("nan")])
    with pytest.raises(ValueError, match="distill_target"):
        loss(data)
    # Keys are renamed as TorchRL's losses' are.
    data["my_regret"] = torch.tensor([0.0, 2.0])
    loss.set_keys(regret="my_regret")
    assert "my_regret" in loss.in_keys
    assert float(loss(data)["distill_expected_regret"]) == pytest.approx(1.0)
