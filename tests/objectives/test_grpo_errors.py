"""GRPOLoss: bad keys, options and inputs are clear errors; masked garbage is ignored."""

from __future__ import annotations

import pytest
import torch
from objectives_builders import branch_batch, categorical_actor, continuous_actor
from tensordict import TensorDict

from torchrl_grpo.objectives import GRPOLoss


def total_loss(out: TensorDict) -> torch.Tensor:
    return sum(v for k, v in out.items() if k.startswith("loss_"))


@pytest.mark.parametrize("key", ["advantage", "mask", "action"])
def test_missing_key_is_an_error(key):
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3))
    del td[key]
    with pytest.raises(ValueError, match=key):
        GRPOLoss(actor)(td)


def test_flat_trajectory_aggregation_needs_ids():
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3)).reshape(-1)
    del td["branch"]
    with pytest.raises(ValueError, match="branch"):
        GRPOLoss(actor, aggregation="grpo")(td)
    GRPOLoss(actor, aggregation="dapo")(td)  # a plain mean needs no ids


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"aggregation": "seq_mean"}, "aggregation"),
        ({"kl_estimator": "k4"}, "kl_estimator"),
        ({"clip_epsilon": 1.0}, "clip_epsilon"),
        ({"clip_epsilon": (0.2, 0.3, 0.4)}, "clip_epsilon"),
        ({"dual_clip": 1.0}, "dual_clip"),
        ({"max_steps": 0}, "max_steps"),
        ({"dual_clip": float("nan")}, "dual_clip"),
        ({"kl_to_ref_coeff": -1.0}, "kl_to_ref_coeff"),
        ({"kl_to_ref_coeff": float("inf")}, "kl_to_ref_coeff"),
        ({"entropy_coeff": float("nan")}, "entropy_coeff"),
        ({"entropy_coeff": -0.01}, "entropy_coeff"),
        ({"clip_epsilon": float("nan")}, "clip_epsilon"),
    ],
)
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        GRPOLoss(categorical_actor(), **kwargs)


def test_analytic_kl_without_closed_form_is_a_clear_error():
    actor = continuous_actor("truncated_normal")
    td = branch_batch(actor, (1, 2, 2))
    GRPOLoss(actor, kl_to_ref_coeff=0.1, kl_estimator="k3")(td.clone())  # works
    loss = GRPOLoss(actor, kl_to_ref_coeff=0.1, kl_estimator="analytic")
    with pytest.raises(ValueError, match="no analytic KL between TruncatedNormal"):
        loss(td)


def test_coefficients_are_schedulable():
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3))
    loss = GRPOLoss(actor, clip_epsilon=(0.2, 0.28), kl_to_ref_coeff=0.1)
    first = loss(td.clone())["loss_entropy"]
    loss.entropy_coeff = 0.02  # the default is 0.01
    torch.testing.assert_close(loss(td.clone())["loss_entropy"], 2 * first)
    loss.clip_epsilon_high = 0.5
    assert loss.clip_epsilon_high.item() == pytest.approx(0.5)
    assert isinstance(loss.kl_to_ref_coeff, torch.Tensor)


# ------------------------------------------------------------- value checks
def nan_actor():
    actor = categorical_actor()
    with torch.no_grad():
        actor.module[0].module[-1].bias.fill_(float("nan"))
    return actor


@pytest.mark.parametrize(
    "corrupt,match",
    [
        (lambda td: td["advantage"].__setitem__((0, 1, 2), float("nan")), "'advantage'"),
        (lambda td: td["advantage"].__setitem__((1, 0, 0), float("inf")), "'advantage'"),
        (lambda td: td["action_log_prob"].__setitem__((0, 0, 1), float("nan")), "action_log_"),
        (lambda td: td["action_log_prob"].__setitem__((0, 0, 1), -float("inf")), "action_log_"),
        (lambda td: td.set("ref_log_prob", torch.full((2, 2, 3), float("nan"))), "ref_log_"),
    ],
)
def test_non_finite_inputs_are_a_clear_error(corrupt, match):
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3))
    corrupt(td)
    loss = GRPOLoss(actor, kl_to_ref_coeff=0.1)
    with pytest.raises(ValueError, match=rf"{match}.*(NaN|infinite)"):
        loss(td.clone())
    # with the checks off the same input gives a NaN loss, as it always did
    loss.check_values = False
    assert not torch.isfinite(total_loss(loss(td.clone()))).all()


def test_non_finite_values_on_masked_steps_are_ignored():
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3))
    td["mask"][0, 1, 2] = False
    td["advantage"][0, 1, 2] = float("nan")
    td["action_log_prob"][0, 1, 2] = float("nan")
    assert torch.isfinite(total_loss(GRPOLoss(actor)(td))).all()


def test_a_non_finite_policy_log_prob_is_a_clear_error():
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3))
    with pytest.raises(ValueError, match="log-prob of the current policy.*NaN"):
        GRPOLoss(nan_actor())(td)


def test_finite_values_whose_sum_overflows_pass_the_check():
    from torchrl_grpo.objectives.loss_checks import check_finite

    check_finite({"'advantage'": torch.full((4,), 3e38)})  # the sum is inf, no value is
    with pytest.raises(ValueError, match="1 of 5 valid steps"):
        check_finite({"'advantage'": torch.tensor([3e38, 3e38, 3e38, 3e38, float("inf")])})
