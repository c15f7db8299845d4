"""The expected-regret group fit (``algo.group_fit_loss=regret``): by hand, and in a run."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))

from train_helpers import REPLAY, csv_scalars, train_run  # noqa: E402

import torchrl_grpo.experimental  # noqa: E402, F401  (registers the fit)
from torchrl_grpo.training.algos.enumerated import GROUP_FITS, distill_targets  # noqa: E402

pytestmark = pytest.mark.experimental


def _fitted_probability_of_action_0(loss_name: str) -> float:
    # Two roots the policy cannot tell apart (the same observation), actions 0 and 1
    # tried from each. At the first, action 1 loses 10; at the second, action 0 loses 1.
    data = TensorDict(
        observation=torch.ones(4, 1),
        action=torch.tensor([0, 1, 0, 1]),
        advantage=torch.tensor([[5.0], [-5.0], [-0.5], [0.5]]),
        group_id=torch.tensor([0, 0, 1, 1]),
        batch_size=[4],
    )
    data = distill_targets(data, 0.0, loss=loss_name)
    net = TensorDictModule(torch.nn.Linear(1, 2), ["observation"], ["logits"])
    actor = ProbabilisticActor(net, ["logits"], distribution_class=torch.distributions.Categorical)
    loss = GROUP_FITS[loss_name].make_loss(actor, 1.0, 0.0)
    optim = torch.optim.Adam(actor.parameters(), lr=0.05)
    for _ in range(300):
        optim.zero_grad()
        loss(data)["loss_distill"].backward()
        optim.step()
    return float(actor.get_dist(data[:1]).probs[0, 0])


def test_the_regret_fit_plays_the_action_that_costs_less_where_roots_look_alike():
    # Regrets: action 0 costs 0 and 1 (mean 0.5), action 1 costs 10 and 0 (mean 5).
    assert _fitted_probability_of_action_0("regret") > 0.9
    # The best-set cross-entropy splits the two roots' best actions evenly.
    assert _fitted_probability_of_action_0("cross_entropy") == pytest.approx(0.5, abs=0.02)


def test_the_targets_are_the_rows_regrets_and_the_hard_best_set():
    data = TensorDict(
        advantage=torch.tensor([[1.0], [-2.0], [1.0], [0.0], [3.0]]),
        group_id=torch.tensor([7, 7, 7, 9, 9]),
        batch_size=[5],
    )
    out = distill_targets(data, 0.5, loss="regret")
    assert out["distill_target"].squeeze(-1).tolist() == [0.0, 3.0, 0.0, 3.0, 0.0]
    assert out["distill_weight"].squeeze(-1).tolist() == [0.5, 0.0, 0.5, 0.0, 1.0]


def test_a_run_trains_on_it(tmp_path):
    overrides = [*REPLAY, "algo.group_fit_loss=regret", "logger=csv"]
    trainer = train_run(tmp_path, "regret", [*overrides, "experiment.total_frames=60"])
    stored = trainer.algo.replay[:]
    advantage = stored["advantage"].reshape(-1, 5)
    regret = advantage.max(-1, keepdim=True).values - advantage
    torch.testing.assert_close(stored["distill_target"].reshape(-1, 5), regret)
    scalars = csv_scalars(tmp_path / "regret")
    expected = scalars["train/distill_expected_regret"]
    assert len(expected) == trainer.iteration and all(v >= 0 for v in expected)
    # loss_distill = coeff (1) * (expected regret + ANCHOR * cross-entropy): never below it.
    assert all(total >= v for total, v in zip(scalars["train/loss_distill"], expected, strict=True))
