"""benchmarks/lab/search_labels.py: the label statistics, by hand."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "lab"))

from search_labels import label_stats, visit  # noqa: E402

pytestmark = pytest.mark.experimental


def test_label_stats_by_hand():
    scores = torch.tensor(
        [[1.0, 1.0, 0.0, 0.0, 0.0], [0.0, 2.0, 1.0, 0.0, 0.0]], dtype=torch.float64
    )
    action = torch.tensor([1, 2])  # in the tied best set; one below the best
    stats = label_stats(scores, action)
    assert stats["best set > 1 action"] == 0.5 and stats["mean size of the best set"] == 1.5
    assert stats["network's action in the best set"] == 0.5
    assert stats["network's action == argmax label"] == 0.0  # the tie goes to LANE_LEFT
    assert stats["regret > 0.1"] == 0.5 and stats["regret > 1"] == 0.0
    assert stats["argmax label LANE_LEFT"] == 0.5 and stats["tied label LANE_LEFT"] == 1.0


def test_one_step_scores_are_the_rewards_the_driven_episodes_get():
    from torchrl_grpo.modules import make_scripted_policy

    # Horizon 1: an action's score is its immediate reward, so the score of the action
    # SLOWER actually played is the reward the driven episode got for it.
    data = visit(make_scripted_policy("slower"), "highway-fast-v0", [0, 1], 1, max_steps=3)
    assert data["scores"].shape == (6, 5) and (data["action"] == 4).all()
    played = data["scores"][:, 4]
    assert torch.allclose(played, data["reward"].double(), atol=1e-6)
    assert not torch.allclose(data["scores"][:, 3], played)  # FASTER scores otherwise


def test_regret_loss_by_hand():
    from search_fit import regret_loss

    logits = torch.zeros(1, 5, requires_grad=True)  # uniform
    scores = torch.tensor([[1.0, 0.0, 0.0, 0.0, 1.0]])  # two tied best actions
    loss = regret_loss(logits, scores, logits.detach(), beta=0.5)
    assert torch.isclose(loss, torch.tensor(0.6))  # 3 of 5 actions lose 1; KL to itself 0
    loss.backward()
    grad = logits.grad[0]
    assert grad[0] == grad[4] < 0 < grad[1] == grad[2] == grad[3]  # the ties alike
