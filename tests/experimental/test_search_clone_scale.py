"""search_clone_scale's error measures and label pooling, against hand-computed figures."""

import argparse

import clone_nets
import pytest
import search_clone_scale
import torch

from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.training import compose_config, make_env, make_policy
from torchrl_grpo.training.checkpoint import save_checkpoint
from torchrl_grpo.training.config import to_container

pytestmark = pytest.mark.experimental


def test_errors_tell_a_crash_from_slowness():
    # Three states, three actions. State 0: the argmax (action 2) is the best: no error.
    # State 1: the argmax (action 0) loses 2 to the best and its branch crashes where
    # action 1's does not: a crash error. State 2: the argmax (action 1) loses 1.5 to the
    # best, whose branch crashes, and its own does not: slowness, not a crash error.
    scores = torch.tensor([[0.0, 1.0, 3.0], [5.0, 7.0, 6.0], [9.0, 7.5, 8.0]])
    crashed = torch.tensor([[False, False, False], [True, False, False], [True, False, True]])
    logits = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    e = search_clone_scale.errors(logits, scores, crashed)
    assert e["accuracy"] == pytest.approx(1 / 3)
    assert e["regret"] == pytest.approx((0.0 + 2.0 + 1.5) / 3)
    assert e["regret > 1"] == pytest.approx(2 / 3)
    assert e["crash error"] == pytest.approx(1 / 3)


def test_a_state_where_every_branch_crashes_is_no_crash_error():
    scores = torch.tensor([[-1.0, -2.0]])
    crashed = torch.tensor([[True, True]])
    e = search_clone_scale.errors(torch.tensor([[0.0, 1.0]]), scores, crashed)
    assert e["crash error"] == 0.0 and e["regret"] == pytest.approx(1.0)


def _labels(path, seeds, n):
    torch.save(
        {
            "observation": torch.full((n, 2, 3), float(seeds[0])),
            "scores": torch.zeros(n, 5),
            "crashed": torch.zeros(n, 5, dtype=torch.bool),
            "seeds": torch.tensor(seeds),
        },
        path,
    )
    return str(path)


def test_label_files_pool_and_refuse_shared_seeds(tmp_path):
    a = _labels(tmp_path / "a.pt", [100, 110], 4)
    b = _labels(tmp_path / "b.pt", [110, 120], 3)
    pooled = search_clone_scale.load_labels([b, a])
    assert pooled["observation"].shape == (7, 2, 3) and pooled["crashed"].shape == (7, 5)
    assert pooled["seeds"].tolist() == [[100, 110], [110, 120]]
    c = _labels(tmp_path / "c.pt", [115, 130], 2)
    with pytest.raises(SystemExit, match="share seeds"):
        search_clone_scale.load_labels([a, b, c])


def test_mean_logits_average_the_members():
    first, second = torch.nn.Linear(2, 3), torch.nn.Linear(2, 3)
    x = torch.tensor([[1.0, -2.0]])
    mean = search_clone_scale.MeanLogits([first, second])
    assert torch.allclose(mean(x), (first(x) + second(x)) / 2)


def _run(path, overrides: list[str]) -> str:
    # A checkpoint as a training run writes it, untrained: what heldout reads of a run.
    cfg = compose_config(["experiment=smoke", "model=mlp", *overrides])
    policy = make_policy(cfg.model, make_env(cfg.env, seed=0))
    state = {"config": to_container(cfg), "policy": policy.state_dict()}
    return str(save_checkpoint(state, path))


def test_heldout_pairs_the_fit_against_every_baseline_and_refuses_another_ppo(tmp_path, capsys):
    tail = _run(tmp_path / "run.pt", [])
    ppo = _run(tmp_path / "ppo.pt", ["seed=1"])
    layout = KinematicsLayout()
    x = torch.zeros(4, layout.n_vehicles * layout.n_features)
    fit = clone_nets.CloneNet(clone_nets.make_trunk("flat", layout, x, 8), 8, 5, True)
    torch.save(fit, tmp_path / "fit.pt")
    args = argparse.Namespace(
        tail=tail, net=[str(tmp_path / "fit.pt")], ppo=ppo, aversion=100.0,
        episodes=2, seed=0, workers=1,
    )  # fmt: skip
    search_clone_scale.heldout(args)
    out = capsys.readouterr().out
    for name in ("always-SLOWER", "the rule policy", "the run, greedy", "PPO, greedy"):
        assert f"- {name}: " in out and f"vs {name}: return" in out
    args.ppo = _run(tmp_path / "other.pt", ["+env.config.lanes_count=4"])
    with pytest.raises(ValueError, match="--ppo"):
        search_clone_scale.heldout(args)
