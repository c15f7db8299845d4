"""``CrashHead``'s margin: the greedy choice never takes an action riskier than SLOWER."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import CrashHead
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.modules.crash_head import BARRED, acting_greedily
from torchrl_grpo.modules.scripted.actions import SLOWER
from torchrl_grpo.training.group_schemas import MLPModelConfig
from torchrl_grpo.training.model_builder import make_policy, set_crash_margin


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def _head(logits: list[float], risks: list[float], **kw) -> CrashHead:
    table = torch.tensor([logits + [_logit(p) for p in risks]], dtype=torch.float64)
    # Observation i picks row i of the table: the network's outputs, set by hand.
    return CrashHead(nn.Embedding.from_pretrained(table, freeze=False), len(logits), **kw)


def _greedy(head: CrashHead) -> torch.Tensor:
    with acting_greedily():
        return head(torch.tensor([0]))


def test_an_action_riskier_than_the_fallback_by_more_than_the_margin_is_barred():
    # Fallback 0 at p = 0.10 and a margin of 0.05: 0.30 is barred, 0.12 and 0.15 are not.
    head = _head([1.0, 5.0, 2.0, 0.5], [0.10, 0.30, 0.12, 0.15], margin=0.05, fallback=0)
    out = _greedy(head).detach()
    floor = 0.5 - BARRED  # below the lowest logit of all four
    torch.testing.assert_close(out, torch.tensor([[1.0, floor, 2.0, 0.5]], dtype=torch.float64))
    assert int(out.argmax()) == 2  # not action 1, the one the logits prefer
    assert float(torch.softmax(out, -1)[0, 1]) < 1e-12


def test_allowed_is_the_bar_the_greedy_choice_applies():
    # Fallback 0 at p = 0.10, margin 0.05: the same bar as the test above, as a mask.
    head = _head([1.0, 5.0, 2.0, 0.5], [0.10, 0.30, 0.12, 0.15], margin=0.05, fallback=0)
    assert head.allowed(torch.tensor([0])).tolist() == [[True, False, True, True]]
    assert torch.equal(head.allowed(torch.tensor([0])), _greedy(head) > 0.5 - BARRED)
    # Without a margin nothing is barred, and outside acting_greedily the mask still holds.
    head.set_margin(None)
    assert head.allowed(torch.tensor([0])).all()


def test_the_margin_applies_after_the_aversion():
    head = _head([1.0, 3.0], [0.5, 0.75], aversion=2.0, margin=0.2, fallback=1)
    # The fallback is never barred, however risky; action 0 is safer, so it stays too.
    expected = [1.0 + 2 * math.log(0.5), 3.0 + 2 * math.log(0.25)]
    torch.testing.assert_close(_greedy(head), torch.tensor([expected], dtype=torch.float64))
    # A barred action sits BARRED below the lowest logit after the aversion.
    barred = _head([1.0, 3.0, 0.0], [0.1, 0.5, 0.1], aversion=2.0, margin=0.1, fallback=0)
    low = 2 * math.log(0.9)
    expected = [1.0 + low, low - BARRED, low]
    torch.testing.assert_close(_greedy(barred), torch.tensor([expected], dtype=torch.float64))
    # A margin of 0 keeps exactly the actions no riskier than the fallback.
    strict = _head([4.0, 1.0, 2.0], [0.2, 0.1, 0.1 + 1e-6], margin=0.0, fallback=1)
    assert _greedy(strict)[0].argmax() == 1


def test_sampling_and_the_losses_see_every_action():
    head = _head([1.0, 5.0, 2.0], [0.1, 0.9, 0.1], margin=0.01, fallback=0)
    plain = torch.tensor([[1.0, 5.0, 2.0]], dtype=torch.float64)
    # TorchRL's losses run under DETERMINISTIC: the exploration type does not bar.
    for mode in (ExplorationType.RANDOM, ExplorationType.DETERMINISTIC, None):
        with set_exploration_type(mode):
            torch.testing.assert_close(head(torch.tensor([0])), plain)
    assert int(_greedy(head).argmax()) == 2


def test_barred_logits_train_nothing_and_the_head_only_through_its_own_loss():
    head = _head([1.0, 5.0, 2.0], [0.1, 0.9, 0.1], margin=0.01, fallback=0)
    _greedy(head).sum().backward()
    # Allowed logits carry the gradient; the barred one and every crash logit get none
    # (the floor is detached).
    assert head.net.weight.grad.tolist() == [[1.0, 0.0, 1.0, 0.0, 0.0, 0.0]]


def test_bad_margins_and_fallbacks_are_named():
    net = nn.Linear(2, 4)
    with pytest.raises(ValueError, match="margin must be a probability in \\[0, 1\\], got -0.1"):
        CrashHead(net, 2, margin=-0.1, fallback=0)
    with pytest.raises(ValueError, match="margin must be a probability in \\[0, 1\\], got nan"):
        CrashHead(net, 2, margin=float("nan"), fallback=0)
    with pytest.raises(ValueError, match="index of a fallback action in \\[0, 2\\), got None"):
        CrashHead(net, 2, margin=0.1)
    with pytest.raises(ValueError, match="index of a fallback action in \\[0, 2\\), got 2"):
        CrashHead(net, 2, margin=0.1, fallback=2)


def test_model_crash_margin_keeps_slower_and_needs_the_crash_head():
    torch.manual_seed(0)
    env = HighwayEnv(seed=0)
    cfg = OmegaConf.structured(MLPModelConfig)
    cfg.crash_head, cfg.crash_margin = True, 0.01
    policy, state = make_policy(cfg, env), env.reset()
    head = policy.module[0].module
    assert isinstance(head, CrashHead)
    assert (head.margin, head.fallback) == (0.01, SLOWER)
    data = DeterministicActor(policy)(state.clone())  # every evaluation acts through it
    assert torch.isfinite(data["action_log_prob"]).all()
    with acting_greedily():
        assert torch.equal(data["logits"], policy(state.clone())["logits"])
    plain = policy(state.clone())["logits"]
    risk = torch.sigmoid(head.crash_logits(state["observation"]))
    barred = risk > risk[..., SLOWER] + 0.01
    assert barred.any() and not barred.all()  # an untrained head: some either way
    assert torch.equal(data["logits"][~barred], plain[~barred])
    assert (data["logits"][barred] == plain.min() - BARRED).all()
    cfg.crash_head = False
    with pytest.raises(ValueError, match="model.crash_margin=0.01 .* needs model.crash_head=true"):
        make_policy(cfg, env)


def test_set_crash_margin_drives_a_built_policy_as_if_trained_with_that_margin():
    # A trained run driven at another margin (bench_scenarios.py --crash-margin) acts as
    # the same weights built with model.crash_margin would, and None lifts the bar.
    torch.manual_seed(0)
    env = HighwayEnv(seed=0)
    fields = OmegaConf.to_container(OmegaConf.structured(MLPModelConfig))
    cfg = OmegaConf.create({**fields, "crash_head": True, "ensemble": 2})  # model=lab's key
    plain, state = make_policy(cfg, env), env.reset()
    cfg.crash_margin = 0.01
    barred = make_policy(cfg, env)
    barred.load_state_dict(plain.state_dict())
    set_crash_margin(plain, 0.01)
    heads = [m for m in plain.modules() if isinstance(m, CrashHead)]
    assert [(h.margin, h.fallback) for h in heads] == [(0.01, SLOWER)] * 2
    with acting_greedily():
        assert torch.equal(plain(state.clone())["logits"], barred(state.clone())["logits"])
        set_crash_margin(plain, None)
        assert all(h.margin is None for h in heads)
        lifted = plain(state.clone())["logits"]
    assert torch.equal(lifted, barred(state.clone())["logits"])  # sampling sees every action
    with pytest.raises(ValueError, match="margin must be a probability in \\[0, 1\\], got 2"):
        set_crash_margin(plain, 2.0)
    cfg.crash_head, cfg.crash_margin = False, None
    with pytest.raises(ValueError, match="this policy has none .*model.crash_head=true"):
        set_crash_margin(make_policy(cfg, env), 0.01)
