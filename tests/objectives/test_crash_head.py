"""CrashHead and CrashHeadLoss against cross-entropies and logits computed by hand."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from torchrl_grpo.modules import CrashHead
from torchrl_grpo.objectives import CrashHeadLoss
from torchrl_grpo.training.algos.enumerated import branch_crashed


class _Table(nn.Module):
    """Row ``i`` of the observation picks row ``i`` of a parameter table."""

    def __init__(self, table: torch.Tensor) -> None:
        super().__init__()
        self.table = nn.Parameter(table)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.table[state]


def test_the_loss_is_the_mean_cross_entropy_of_each_rows_action():
    # Two states, two actions: crash logits (columns 2, 3) of 0 and log 3 (p = 1/2, 3/4).
    table = torch.tensor([[0.0, 0.0, 0.0, math.log(3)], [0.0, 0.0, math.log(3), 0.0]])
    head = CrashHead(_Table(table), 2)
    data = TensorDict(
        observation=torch.tensor([0, 0, 1, 1]),
        action=torch.tensor([0, 1, 0, 1]),
        branch_crashed=torch.tensor([True, False, True, True]),
        batch_size=[4],
    )
    out = CrashHeadLoss(head, coeff=2.0)(data)
    # -log(1/2), -log(1/4), -log(3/4), -log(1/2)
    expected = (math.log(2) + math.log(4) + math.log(4 / 3) + math.log(2)) / 4
    assert float(out["crash_head_bce"]) == pytest.approx(expected)
    assert float(out["loss_crash_head"].detach()) == pytest.approx(2 * expected)
    # Right side of 1/2: p = 1/2 reads "no crash" (rows 0 and 3 wrong), p = 3/4 "crash"
    # (row 1 wrong, row 2 right).
    assert float(out["crash_head_accuracy"]) == pytest.approx(0.25)
    out["loss_crash_head"].backward()
    # Only the crash logits of the rows' actions get a gradient: sigmoid(l) - label, / 4.
    grad = head.net.table.grad
    assert torch.equal(grad[:, :2], torch.zeros(2, 2))
    expected_grad = 2.0 * torch.tensor([[0.5 - 1, 0.75 - 0], [0.75 - 1, 0.5 - 1]]) / 4
    torch.testing.assert_close(grad[:, 2:], expected_grad)


def test_a_probability_label_gives_the_soft_cross_entropy_and_bad_labels_are_named():
    # p = 1/2 and 3/4; labels 1/4 and 1 (a bootstrapped label and a crash).
    table = torch.tensor([[0.0, 0.0, 0.0, math.log(3)]])
    head = CrashHead(_Table(table), 2)
    data = TensorDict(
        observation=torch.tensor([0, 0]),
        action=torch.tensor([0, 1]),
        branch_crashed=torch.tensor([0.25, 1.0]),
        batch_size=[2],
    )
    out = CrashHeadLoss(head, coeff=1.0)(data)
    # -(1/4 log 1/2 + 3/4 log 1/2) = log 2, and -log 3/4.
    expected = (math.log(2) + math.log(4 / 3)) / 2
    assert float(out["crash_head_bce"]) == pytest.approx(expected)
    # Label 1/4 reads "no crash" and p = 1/2 too; label 1 and p = 3/4 read "crash".
    assert float(out["crash_head_accuracy"]) == 1.0
    for bad in (1.5, -0.1, float("nan")):
        data["branch_crashed"] = torch.tensor([0.25, bad])
        with pytest.raises(ValueError, match="crash label 'branch_crashed' must lie in"):
            CrashHeadLoss(head, coeff=1.0)(data)


def test_aversion_adds_the_log_survival_probability_and_trains_nothing_through_it():
    table = torch.tensor([[1.0, 2.0, math.log(3), -math.log(3)]])
    head = CrashHead(_Table(table), 2, aversion=4.0)
    logits = head(torch.tensor([0]))
    # p = 3/4 and 1/4: log(1 - p) = log(1/4) and log(3/4).
    torch.testing.assert_close(
        logits, torch.tensor([[1.0 + 4 * math.log(0.25), 2.0 + 4 * math.log(0.75)]])
    )
    logits.sum().backward()
    assert torch.equal(head.net.table.grad, torch.tensor([[1.0, 1.0, 0.0, 0.0]]))
    plain = CrashHead(_Table(table), 2)
    torch.testing.assert_close(plain(torch.tensor([0])), table[:, :2])


def test_labels_mark_every_step_of_a_branch_the_env_ended():
    mask = torch.tensor([[[True, True, True], [True, True, False], [True, False, False]]])
    terminated = torch.zeros(1, 3, 3, 1, dtype=torch.bool)
    terminated[0, 1, 1] = True  # branch 1 crashes at its last step
    terminated[0, 2, 2] = True  # branch 2's flag lies past its end: not its crash
    batch = TensorDict({"mask": mask, ("next", "terminated"): terminated}, batch_size=[1, 3, 3])
    assert branch_crashed(batch).tolist() == [[[False] * 3, [True] * 3, [False] * 3]]


def test_bad_heads_and_arguments_are_named():
    with pytest.raises(TypeError, match="no crash_logits"):
        CrashHeadLoss(nn.Linear(2, 2), coeff=1.0)
    head = CrashHead(nn.Linear(2, 4), 2)
    with pytest.raises(ValueError, match="coeff must be a finite number > 0"):
        CrashHeadLoss(head, coeff=0.0)
    with pytest.raises(ValueError, match="aversion must be a finite number >= 0"):
        CrashHead(nn.Linear(2, 4), 2, aversion=-1.0)
    with pytest.raises(ValueError, match="2 \\* n_actions = 6 outputs, got 4"):
        CrashHead(nn.Linear(2, 4), 3)(torch.zeros(1, 2))
    data = TensorDict(observation=torch.zeros(1, 2), action=torch.tensor([0]), batch_size=[1])
    with pytest.raises(ValueError, match="no 'branch_crashed' entry"):
        CrashHeadLoss(head, coeff=1.0)(data)
