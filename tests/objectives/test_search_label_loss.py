"""SearchLabelLoss: each term against numbers worked by hand, and its errors."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_grpo.modules import CrashHead
from torchrl_grpo.objectives import SearchLabelLoss


def head_with(policy: list[float], crash: list[float], aversion: float = 0.0) -> CrashHead:
    """A crash head whose net gives every state these policy and crash logits."""
    net = torch.nn.Linear(1, 2 * len(policy))
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(torch.tensor(policy + crash))
    return CrashHead(net, len(policy), aversion=aversion)


def labels(scores: list[list[float]], crashed: list[list[bool]]) -> TensorDict:
    n = len(scores)
    return TensorDict(
        observation=torch.zeros(n, 1),
        search_scores=torch.tensor(scores),
        search_crashed=torch.tensor(crashed),
        batch_size=[n],
    )


def test_each_term_is_the_number_worked_by_hand():
    # pi = (1/2, 1/4, 1/4); p_crash = (1/2, 1/2, 1/2).
    head = head_with([math.log(2.0), 0.0, 0.0], [0.0, 0.0, 0.0])
    # State 1: actions 1 and 2 tie for the best (3.0), action 0 crashes and loses 2.
    # State 2: action 0 is the best alone; action 2 loses 1.
    data = labels([[1.0, 3.0, 3.0], [2.0, 2.0 - 1e-3, 1.0]], [[True, False, False], [False] * 3])
    out = SearchLabelLoss(head, regret_coeff=2.0, crash_coeff=0.5)(data)
    ce_1 = -(0.5 * math.log(0.25) + 0.5 * math.log(0.25))
    ce_2 = -math.log(0.5)
    assert float(out["loss_best_set"]) == pytest.approx((ce_1 + ce_2) / 2, abs=1e-6)
    regret_1, regret_2 = 0.5 * 2.0, 0.25 * 1e-3 + 0.25 * 1.0
    assert float(out["loss_search_regret"]) == pytest.approx(
        2.0 * (regret_1 + regret_2) / 2, abs=1e-5
    )
    assert float(out["loss_search_crash"]) == pytest.approx(0.5 * math.log(2.0), abs=1e-6)
    # It acts on action 0: a crash it could avoid on state 1, the best on state 2.
    assert float(out["search_accuracy"]) == 0.5
    assert float(out["search_regret"]) == pytest.approx(1.0)
    assert float(out["search_crash_error"]) == 0.5


def test_the_diagnostics_follow_the_actions_the_crash_head_weighs():
    # The policy prefers action 0, but its head is nearly sure that action 0 crashes.
    head = head_with([1.0, 0.0], [8.0, -8.0], aversion=3.0)
    data = labels([[0.0, 1.0]], [[True, False]])
    out = SearchLabelLoss(head, regret_coeff=0.0, crash_coeff=1.0)(data)
    assert float(out["search_accuracy"]) == 1.0 and float(out["search_crash_error"]) == 0.0
    # The cross-entropy fits the policy's own logits, not those the head weighs.
    assert float(out["loss_best_set"]) == pytest.approx(-math.log(1 / (1 + math.e)), abs=1e-6)
    assert float(out["loss_search_regret"]) == 0.0


def test_a_crash_everywhere_is_no_crash_error():
    head = head_with([0.0, 0.0], [0.0, 0.0])
    out = SearchLabelLoss(head, regret_coeff=1.0, crash_coeff=1.0)(
        labels([[0.0, 0.0]], [[True, True]])
    )
    assert float(out["search_crash_error"]) == 0.0


def test_bad_arguments_and_labels_are_named():
    with pytest.raises(TypeError, match="Linear has no crash_logits"):
        SearchLabelLoss(torch.nn.Linear(1, 4), regret_coeff=1.0, crash_coeff=1.0)
    head = head_with([0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ValueError, match="regret_coeff must be a finite number >= 0"):
        SearchLabelLoss(head, regret_coeff=-1.0, crash_coeff=1.0)
    with pytest.raises(ValueError, match="coeff must be a finite number > 0"):
        SearchLabelLoss(head, regret_coeff=1.0, crash_coeff=0.0)
    loss = SearchLabelLoss(head, regret_coeff=1.0, crash_coeff=1.0)
    with pytest.raises(ValueError, match=r"labelled \(1, 3\) scores .* the policy has \(1, 2\)"):
        loss(labels([[0.0, 1.0, 2.0]], [[False] * 3]))
    with pytest.raises(ValueError, match="the search's scores"):
        loss(labels([[0.0, float("nan")]], [[False] * 2]))
    loss.set_keys(scores="q")
    with pytest.raises(ValueError, match="no 'q' entry"):
        loss(labels([[0.0, 1.0]], [[False] * 2]))
