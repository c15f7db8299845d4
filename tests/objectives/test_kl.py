"""KL estimators against the analytic KL of Categorical and Normal on sampled data."""

from __future__ import annotations

import math

import pytest
import torch
from torch.distributions import Categorical, Normal, kl_divergence

from torchrl_grpo.objectives import kl_estimate
from torchrl_grpo.objectives.kl import analytic_kl

N_SAMPLES = 200_000


def test_hand_values():
    lp, ref = torch.tensor([-1.0, -2.0, -0.5]), torch.tensor([-1.5, -1.0, -0.5])
    log_r = ref - lp  # -0.5, 1.0, 0.0
    torch.testing.assert_close(kl_estimate(lp, ref, "k1"), torch.tensor([0.5, -1.0, 0.0]))
    torch.testing.assert_close(kl_estimate(lp, ref, "k2"), torch.tensor([0.125, 0.5, 0.0]))
    k3 = torch.tensor([math.exp(-0.5) - 1 + 0.5, math.e - 1 - 1.0, 0.0])
    torch.testing.assert_close(kl_estimate(lp, ref, "k3"), k3)
    assert torch.equal(log_r, torch.tensor([-0.5, 1.0, 0.0]))
    with pytest.raises(ValueError, match="estimator"):
        kl_estimate(lp, ref, "k4")


def pairs():
    yield (
        "categorical",
        Categorical(logits=torch.tensor([0.0, 0.5, -1.0, 1.5])),
        Categorical(logits=torch.tensor([0.3, 0.0, -0.5, 1.0])),
    )
    yield (
        "normal",
        Normal(torch.tensor(0.0), torch.tensor(1.0)),
        Normal(torch.tensor(0.3), torch.tensor(1.2)),
    )


@pytest.mark.parametrize("name,p,q", list(pairs()))
@pytest.mark.parametrize("estimator", ["k1", "k3"])
def test_unbiased_estimators_match_analytic_kl(name, p, q, estimator):
    torch.manual_seed(1)
    x = p.sample((N_SAMPLES,))
    k = kl_estimate(p.log_prob(x), q.log_prob(x), estimator)
    exact = analytic_kl(p, q)
    # five standard errors: fails for a biased estimator, not for sampling noise
    stderr = k.std() / math.sqrt(N_SAMPLES)
    assert abs(k.mean() - exact) < 5 * stderr, (name, float(k.mean()), float(exact))
    if estimator == "k3":
        assert (k >= 0).all()


def close_pairs():
    yield (
        "categorical",
        Categorical(logits=torch.tensor([0.0, 0.5, -1.0, 1.5])),
        Categorical(logits=torch.tensor([0.05, 0.45, -0.95, 1.45])),
    )
    yield (
        "normal",
        Normal(torch.tensor(0.0), torch.tensor(1.0)),
        Normal(torch.tensor(0.05), torch.tensor(1.03)),
    )


@pytest.mark.parametrize("name,p,q", list(close_pairs()))
def test_k2_is_second_order_accurate_for_close_policies(name, p, q):
    torch.manual_seed(2)
    x = p.sample((N_SAMPLES,))
    k2 = kl_estimate(p.log_prob(x), q.log_prob(x), "k2")
    exact = float(analytic_kl(p, q))
    assert (k2 >= 0).all()
    assert abs(float(k2.mean()) - exact) < 0.1 * exact, (name, float(k2.mean()), exact)


@pytest.mark.parametrize("name,p,q", list(pairs()))
def test_k2_is_biased_for_distant_policies(name, p, q):
    torch.manual_seed(2)
    x = p.sample((N_SAMPLES,))
    k2 = kl_estimate(p.log_prob(x), q.log_prob(x), "k2")
    stderr = float(k2.std()) / math.sqrt(N_SAMPLES)
    assert abs(float(k2.mean()) - float(analytic_kl(p, q))) > 5 * stderr


def test_analytic_kl_matches_torch_and_rejects_unknown_pairs():
    p = Normal(torch.zeros(3), torch.ones(3))
    q = Normal(torch.ones(3), 2 * torch.ones(3))
    torch.testing.assert_close(analytic_kl(p, q), kl_divergence(p, q))
    with pytest.raises(ValueError, match="no analytic KL between Categorical and Normal"):
        analytic_kl(Categorical(logits=torch.zeros(3)), Normal(0.0, 1.0))
