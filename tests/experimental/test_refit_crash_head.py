"""refit_crash_head: its labels are the episodes' own outcomes, its loss is the hand-computed
one, and its fit moves the crash logits while the anchor holds the policy's."""

import argparse
import math

import pytest
import refit_crash_head as refit
import torch
from omegaconf import OmegaConf
from torch import nn

from torchrl_grpo.modules import ConstantActionPolicy
from torchrl_grpo.modules.crash_head import CrashHead

pytestmark = pytest.mark.experimental

CFG = OmegaConf.create({"scenario": "roundabout-v0", "config": {}, "max_episode_steps": 11})
FASTER = 3


def test_visit_labels_the_episodes_own_crashes_and_counts_every_branch_step():
    visited = refit.visit(CFG, ConstantActionPolicy("FASTER"), episodes=8, seed=40000)
    crashed, greedy = visited["crashed"], visited["greedy"]
    n = crashed.shape[0]
    assert visited["observation"].shape[0] == n and (greedy == FASTER).all()
    # Each state's branch of FASTER then SLOWER is at least as long as one step and at
    # most the episode; the driven steps count too.
    assert 6 * n <= visited["frames"] <= n + 5 * n * 11
    # always-FASTER crashes in about half of the episodes: the last step of each crashed
    # episode is FASTER's own crash there.
    assert crashed[:, FASTER].any()
    assert 0 <= refit.wrong_greedy(crashed, greedy) <= float(crashed[:, FASTER].double().mean())


def test_wrong_greedy_counts_the_taken_actions_that_crash_where_slower_does_not():
    crashed = torch.tensor(
        [
            [0, 0, 0, 1, 0],  # FASTER crashes, SLOWER does not
            [0, 0, 0, 1, 1],  # both crash: lost, not wrong
            [1, 0, 0, 0, 0],  # an action not taken crashes
            [0, 0, 0, 0, 0],
        ],
        dtype=torch.bool,
    )
    greedy = torch.tensor([FASTER, FASTER, 1, 4])
    assert refit.wrong_greedy(crashed, greedy) == 0.25


def test_head_loss_is_the_weighted_cross_entropy_plus_the_anchor():
    net = nn.Linear(2, 10)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.zero_()
    head = CrashHead(net, 5)
    obs = torch.zeros(2, 2)
    crashed = torch.tensor([[1, 0, 0, 0, 0], [0] * 5], dtype=torch.bool)  # one deciding
    start = torch.ones(2, 5)  # the logits sit at 0: a drift of 5 per state
    loss = refit.head_loss(head, obs, crashed, start, weight=4.0, anchor=0.5)
    per_state = 5 * math.log(2)  # every crash logit at 0
    expected = ((4 + 1) * per_state + 2 * 0.5 * 5) / 2
    assert loss.item() == pytest.approx(expected, rel=1e-6)


def test_fit_moves_the_crash_logits_towards_the_labels_and_the_anchor_holds_the_policy():
    torch.manual_seed(0)
    obs = torch.randn(256, 4)
    crashed = (obs[:, :1] > 0).expand(256, 5).clone()  # every action crashes where x0 > 0
    args = argparse.Namespace(epochs=40, lr=1e-2, weight=1.0, anchor=0.0, miss_weight=1.0)
    drifts = {}
    for anchor in (0.0, 100.0):
        torch.manual_seed(1)
        head = CrashHead(nn.Sequential(nn.Linear(4, 16), nn.Tanh(), nn.Linear(16, 10)), 5)
        with torch.no_grad():
            start = head._split(obs)[0]
        before = refit.head_loss(head, obs, crashed, start, 1.0, 0.0)
        args.anchor = anchor
        refit.fit(head, {"observation": obs, "crashed": crashed}, start, args)
        with torch.no_grad():
            after = refit.head_loss(head, obs, crashed, start, 1.0, 0.0)
            drifts[anchor] = float((head._split(obs)[0] - start).abs().max())
        assert after < 0.5 * before
    assert drifts[100.0] < 0.2 * drifts[0.0]


def test_miss_weight_multiplies_only_the_allowed_actions_that_crash_where_slower_does_not():
    net = nn.Linear(2, 10)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.zero_()
        net.bias[5:].copy_(torch.tensor([0.0, 0.0, 3.0, 0.0, 0.0]))  # action 2 looks risky
    head = CrashHead(net, 5, margin=0.01, fallback=4)  # bars action 2 only
    obs = torch.zeros(1, 2)
    # Action 0 crashes and is allowed: a miss. Action 2 crashes but is barred.
    crashed = torch.tensor([[1, 0, 1, 0, 0]], dtype=torch.bool)
    start = torch.zeros(1, 5)
    loss = refit.head_loss(head, obs, crashed, start, weight=1.0, anchor=0.0, miss_weight=10.0)
    log2, barred_hit = math.log(2), math.log1p(math.exp(-3.0))  # -log sigmoid(3)
    assert loss.item() == pytest.approx(10 * log2 + 3 * log2 + barred_hit, rel=1e-6)
