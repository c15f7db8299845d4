"""benchmarks/lab/search_labels.py: the label statistics, by hand."""

from __future__ import annotations

import pytest
import torch
from search_labels import label_stats, visit

from torchrl_grpo.modules import make_scripted_policy

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


def test_a_runs_config_reaches_the_driven_episodes_and_the_branches():
    # A larger observation, as a run's env.config gives it: the states the labels are
    # fitted on are read through it, and the branches' policy sees it too.
    config = {"observation": {"type": "Kinematics", "vehicles_count": 7, "see_behind": True}}
    data = visit(make_scripted_policy("slower"), "highway-fast-v0", [0], 2, 2, config=config)
    assert data["observation"].shape == (2, 7, 5)
    plain = visit(make_scripted_policy("slower"), "highway-fast-v0", [0], 2, 2)
    assert plain["observation"].shape == (2, 5, 5)
    assert torch.equal(data["scores"], plain["scores"])  # the same worlds, other tables


def test_regret_loss_by_hand():
    from search_fit import regret_loss

    logits = torch.zeros(1, 5, requires_grad=True)  # uniform
    scores = torch.tensor([[1.0, 0.0, 0.0, 0.0, 1.0]])  # two tied best actions
    loss = regret_loss(logits, scores, logits.detach(), beta=0.5)
    assert torch.isclose(loss, torch.tensor(0.6))  # 3 of 5 actions lose 1; KL to itself 0
    loss.backward()
    grad = logits.grad[0]
    assert grad[0] == grad[4] < 0 < grad[1] == grad[2] == grad[3]  # the ties alike


def test_crash_flags_mark_the_branches_that_crash_and_scores_equal_the_planners():
    from search_labels import branch_outcomes

    from torchrl_grpo.branching import LookaheadPolicy
    from torchrl_grpo.branching.batched_search import highway_starts
    from torchrl_grpo.envs import TensorHighwayEnv
    from torchrl_grpo.modules import make_scripted_policy

    planner = LookaheadPolicy(TensorHighwayEnv(num_envs=100), make_scripted_policy("aggressive"), 8)
    td = highway_starts(TensorHighwayEnv(num_envs=20, return_state=True), list(range(20)))
    scores, crashed = branch_outcomes(planner, td)
    assert torch.equal(scores, planner.returns(td))
    assert crashed.any() and not crashed.all()
    # A branch that crashes ends at its crash: it earns less than the 8 steps of the others.
    assert scores[crashed].mean() < scores[~crashed].mean()


def test_crash_loss_by_hand():
    from search_fit import crash_loss

    logits = torch.zeros(3, 5, requires_grad=True)  # uniform, and the start too
    crashed = torch.tensor([[1, 0, 0, 0, 0], [0, 0, 0, 0, 0], [1, 1, 1, 1, 1]], dtype=torch.bool)
    loss = crash_loss(logits, crashed, logits.detach(), weight=2.0)
    # Only the first state decides a crash: the target is uniform over the 4 safe actions,
    # a cross-entropy of log 5 against the uniform policy; the others keep a KL of 0.
    assert torch.isclose(loss, 2 * torch.log(torch.tensor(5.0)) / 3)
    loss.backward()
    grad = logits.grad
    assert grad[0, 0] > 0 > grad[0, 1] and torch.allclose(grad[1:], torch.zeros(2, 5), atol=1e-7)
    # With the scores: where no branch crashes, the expected regret pulls (times speed).
    scores = torch.tensor([[0.0, 8, 8, 8, 8], [7, 8, 8, 8, 6], [1, 1, 1, 1, 1]])
    loss = crash_loss(logits, crashed, logits.detach(), 2.0, scores, beta=0.1, speed=0.5)
    assert torch.isclose(loss, (2 * torch.log(torch.tensor(5.0)) + 0.5 * 0.6) / 3)


def test_crash_loss_tilts_the_target_towards_the_safe_actions_that_score_more():
    from search_fit import crash_loss

    logits = torch.zeros(1, 5)
    crashed = torch.tensor([[1, 0, 0, 1, 1]], dtype=torch.bool)  # actions 1 and 2 are safe
    scores = torch.tensor([[0.0, 8.0, 6.0, 0.0, 0.0]])
    tilted = crash_loss(logits, crashed, logits, 1.0, scores, temperature=1.0, speed=0.0)
    # Target over the safe actions: e^0 and e^-2, normalised; the cross-entropy against
    # the uniform policy is log 5 whatever the target, so compare the gradients instead.
    p = torch.tensor([1.0, torch.exp(torch.tensor(-2.0))])
    p = p / p.sum()
    logits = torch.zeros(1, 5, requires_grad=True)
    crash_loss(logits, crashed, logits.detach(), 1.0, scores, temperature=1.0, speed=0.0).backward()
    assert torch.allclose(logits.grad[0, 1:3], 0.2 - p)  # softmax gradient: pi - target
    assert torch.isclose(tilted, torch.log(torch.tensor(5.0)))


def test_a_planner_over_redrawn_copies_labels_as_the_plain_one_when_nothing_is_redrawn():
    from bench_hidden_search import RedrawnSearch

    from torchrl_grpo.envs import TensorHighwayEnv

    seeds = list(range(8))
    plain = visit(make_scripted_policy("aggressive"), "highway-fast-v0", seeds, 4, max_steps=6)
    # Two copies of each state, nothing redrawn: each copy is the plain search's branch,
    # so the mean score is its score and the crash share is its crash flag (0 or 1).
    copies = RedrawnSearch(
        TensorHighwayEnv("highway-fast-v0", num_envs=5 * 2 * len(seeds)), 4, copies=2,
        redraw="none", aggregate="mean", crash_penalty=0.0, seed=0, base="aggressive",
    )  # fmt: skip
    redrawn = visit(make_scripted_policy("aggressive"), "highway-fast-v0", seeds, 4, 6, copies)
    assert torch.equal(redrawn["scores"], plain["scores"])
    assert torch.equal(redrawn["crashed"], plain["crashed"])
    assert torch.equal(redrawn["action"], plain["action"])
    assert plain["crashed"].any() and not plain["crashed"].all()
