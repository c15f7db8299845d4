"""clone_nets' acting rule and trunks, and clone_heads' fit, against hand-computed figures."""

import argparse
import math

import clone_heads
import clone_nets
import pytest
import torch

from torchrl_grpo.modules.kinematics_table import KinematicsLayout

pytestmark = pytest.mark.experimental


def test_the_crash_head_weighs_and_bars_actions_as_written():
    # p_crash = 0.5 and 0.9: with aversion 1 the logits become 0 + log 0.5 and
    # 1 + log 0.1, so the first action wins although the policy prefers the second.
    logits = torch.tensor([[0.0, 1.0]])
    crash = torch.tensor([[0.0, math.log(9.0)]])
    acted = clone_nets.act_logits(logits, crash, aversion=1.0, margin=None)
    assert acted.tolist()[0] == pytest.approx([math.log(0.5), 1.0 + math.log(0.1)])
    assert clone_nets.act_logits(logits, None, 5.0, 0.1).tolist() == logits.tolist()
    # A margin of 0.3 bars the action whose p_crash exceeds the smallest by 0.4.
    barred = clone_nets.act_logits(logits, crash, aversion=0.0, margin=0.3)
    assert barred[0, 0] == 0.0 and barred[0, 1] == float("-inf")
    assert clone_nets.act_logits(logits, crash, 0.0, 0.5).tolist() == logits.tolist()


def _tables(n: int, layout: KinematicsLayout, generator: torch.Generator) -> torch.Tensor:
    rows = torch.randn(n, layout.n_vehicles, layout.n_features, generator=generator)
    rows[..., 0] = (torch.rand(n, layout.n_vehicles, generator=generator) < 0.7).float()
    rows[:, 0, 0] = 1.0
    return rows.flatten(1)


@pytest.mark.parametrize("kind", ["attention", "transformer"])
def test_the_attention_trunks_read_the_other_vehicles_as_a_set_and_keep_presence(kind):
    layout = KinematicsLayout()
    x = _tables(64, layout, torch.Generator().manual_seed(0))
    torch.manual_seed(0)
    trunk = clone_nets.make_trunk(kind, layout, x, 16, embed=16)
    rows = x.reshape(64, 5, 5)
    assert torch.equal(trunk[0](x)[..., 0], rows[..., 0])  # presence is not standardised
    shuffled = rows[:, [0, 3, 1, 4, 2]].flatten(1)  # the ego first, the others reordered
    assert torch.allclose(trunk(x), trunk(shuffled), atol=1e-5)
    absent = rows.clone()
    absent[:, 1:, 1:] = torch.where(absent[:, 1:, :1] > 0.5, absent[:, 1:, 1:], 7.0)
    assert torch.allclose(trunk(x), trunk(absent.flatten(1)), atol=1e-5)
    ego_moved = rows.clone()
    ego_moved[:, 0, 1] += 1.0
    assert not torch.allclose(trunk(x), trunk(ego_moved.flatten(1)), atol=1e-3)


def test_the_flat_and_scene_trunks():
    layout = KinematicsLayout()
    x = _tables(64, layout, torch.Generator().manual_seed(0))
    shuffled = x.reshape(64, 5, 5)[:, [0, 3, 1, 4, 2]].flatten(1)
    flat = clone_nets.make_trunk("flat", layout, x, 16)
    assert not torch.allclose(flat(x), flat(shuffled), atol=1e-3)  # the order is an input
    scene = clone_nets.make_trunk("scene", layout, x, 16)
    assert scene[0](x).shape == (64, 18 + 25) and scene(x).shape == (64, 16)
    with pytest.raises(ValueError, match="unknown trunk 'mlp'"):
        clone_nets.make_trunk("mlp", layout, x, 16)


def test_the_fit_learns_the_best_set_and_the_crash_chance():
    # Inputs that say nothing, so each head can only learn the labels' frequencies: the
    # best set is action 1 in every state, and the branches of actions 0, 1 and 2 crash
    # in an eighth, a half and a quarter of them. The cross-entropy to the best set is
    # smallest at p(1) = 1; the crash head's binary cross-entropy at the frequencies.
    n = 512
    generator = torch.Generator().manual_seed(1)
    crashed = torch.zeros(n, 3, dtype=torch.bool)
    for action, share in enumerate((8, 2, 4)):
        crashed[torch.randperm(n, generator=generator)[: n // share], action] = True
    labels = {
        "observation": torch.zeros(n, 5, 5),
        "scores": torch.tensor([0.0, 1.0, 0.5]).expand(n, 3).clone(),
        "crashed": crashed,
    }
    layout = KinematicsLayout()
    trunk = clone_nets.make_trunk("flat", layout, labels["observation"].flatten(1), 8)
    net = clone_nets.CloneNet(trunk, 8, 3, crash_head=True)
    clone_heads.fit_net(net, labels, torch.arange(n), 400, 0.0, 1.0)
    with torch.no_grad():
        logits, crash = net.heads(labels["observation"][:1].flatten(1))
    assert logits.softmax(-1)[0, 1] > 0.98
    assert crash.sigmoid()[0].tolist() == pytest.approx([0.125, 0.5, 0.25], abs=0.01)


@pytest.mark.parametrize("kind", ["flat", "scene", "attention", "transformer"])
def test_an_unbatched_table_gives_one_action_as_a_batched_one_does(kind):
    # An unbatched env's observation flattens to [V * F]; its action must have no batch
    # dimension, or the env refuses it (found driving a fit on highway-env).
    layout = KinematicsLayout()
    x = _tables(8, layout, torch.Generator().manual_seed(2))
    net = clone_nets.CloneNet(clone_nets.make_trunk(kind, layout, x, 16), 16, 5, True)
    net.aversion = 3.0
    assert net(x[3]).shape == (5,) and net(x.reshape(2, 4, 25)).shape == (2, 4, 5)
    assert torch.allclose(net(x[3]), net(x)[3], atol=1e-6)


def test_the_transformer_has_the_layers_asked_for():
    layout = KinematicsLayout()
    x = _tables(8, layout, torch.Generator().manual_seed(3))
    for layers in (1, 3):
        trunk = clone_nets.make_trunk("transformer", layout, x, 16, embed=16, layers=layers)
        assert len(trunk[1].layers.layers) == layers


def test_a_fit_from_a_saved_fit_starts_from_its_weights(tmp_path):
    # --init: the saved net itself comes back, and a fit at rate 0 leaves it bitwise as
    # saved, so what a further fit changes is the fitting alone.
    layout = KinematicsLayout()
    x = _tables(64, layout, torch.Generator().manual_seed(4))
    torch.manual_seed(0)
    saved = clone_nets.CloneNet(clone_nets.make_trunk("flat", layout, x, 8), 8, 5, True)
    torch.save(saved, tmp_path / "fit.pt")
    args = argparse.Namespace(init=str(tmp_path / "fit.pt"))
    net = clone_heads.new_net(args, layout, "transformer", 1.0, x, 5)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    assert all(torch.equal(before[k], v) for k, v in saved.state_dict().items())
    labels = {
        "observation": x.reshape(64, 5, 5),
        "scores": torch.rand(64, 5, generator=torch.Generator().manual_seed(5)),
        "crashed": torch.zeros(64, 5, dtype=torch.bool),
    }
    clone_heads.fit_net(net, labels, torch.arange(64), 2, 0.0, 1.0, lr=0.0)
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    clone_heads.fit_net(net, labels, torch.arange(64), 2, 0.0, 1.0, lr=1e-2)
    assert not torch.equal(before["policy.weight"], net.state_dict()["policy.weight"])


def test_the_regret_weight_tilts_the_fit_towards_the_cheap_mistake():
    # Inputs that say nothing; action 0 is best in half the states, where action 1 loses
    # 10, and action 1 in the other half, where action 0 loses 0.1. The cross-entropy
    # alone settles at p0 = 1/2. With weight w the loss in p0 is
    # -ln(p0)/2 - ln(1 - p0)/2 + w (0.05 p0 + 5 (1 - p0)), smallest where
    # 1/(2 (1 - p0)) - 1/(2 p0) = 4.95 w: p0 = 0.99 at w = 10 (hand-solved).
    n = 256
    scores = torch.zeros(n, 2)
    scores[: n // 2, 1] = -10.0
    scores[n // 2 :, 0] = -0.1
    labels = {
        "observation": torch.zeros(n, 5, 5),
        "scores": scores,
        "crashed": torch.zeros(n, 2, dtype=torch.bool),
    }
    layout = KinematicsLayout()
    for weight, p0 in ((0.0, 0.5), (10.0, 0.99)):
        trunk = clone_nets.make_trunk("flat", layout, labels["observation"].flatten(1), 8)
        net = clone_nets.CloneNet(trunk, 8, 2, crash_head=False)
        clone_heads.fit_net(net, labels, torch.arange(n), 1500, 0.0, 0.0, regret_weight=weight)
        with torch.no_grad():
            p = net(labels["observation"][:1].flatten(1)).softmax(-1)[0, 0]
        assert float(p) == pytest.approx(p0, abs=0.01)
