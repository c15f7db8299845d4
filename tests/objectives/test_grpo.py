"""GRPOLoss: hand-computed cases, equality with ClipPPOLoss, gradient rule, keys, errors."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from objectives_builders import branch_batch, categorical_actor, continuous_actor, table_actor
from tensordict import TensorDict
from torchrl.objectives import ClipPPOLoss

from torchrl_grpo.objectives import GRPOLoss


def total_loss(out: TensorDict) -> torch.Tensor:
    return sum(v for k, v in out.items() if k.startswith("loss_"))


def grads(loss: torch.Tensor, actor) -> list[torch.Tensor]:
    params = [p for p in actor.parameters() if p.requires_grad]
    return list(torch.autograd.grad(loss, params))


def make_actor(kind: str):
    return categorical_actor() if kind == "categorical" else continuous_actor(kind)


# --------------------------------------------------- equality with ClipPPOLoss
@pytest.mark.parametrize("kind", ["categorical", "independent_normal", "tanh_normal"])
@pytest.mark.parametrize("clip", [0.2, (0.2, 0.28)])
@pytest.mark.parametrize("beta", [None, 0.0])
def test_matches_clip_ppo_when_beta_is_zero(kind, clip, beta):
    actor = make_actor(kind)
    td = branch_batch(actor, (3, 4, 5))
    # TanhNormal has no closed-form entropy: both losses would draw different samples
    entropy = kind != "tanh_normal"
    grpo = GRPOLoss(actor, clip_epsilon=clip, kl_to_ref_coeff=beta, entropy_bonus=entropy)
    ppo = ClipPPOLoss(actor, None, critic_coeff=None, clip_epsilon=clip, entropy_bonus=entropy)
    out_g, out_p = grpo(td.clone()), ppo(td.clone())
    for key in ["loss_objective", "clip_fraction", "kl_approx", "max_ratio", "mean_ratio"] + (
        ["loss_entropy", "entropy"] if entropy else []
    ):
        torch.testing.assert_close(out_g[key], out_p[key], msg=key)
    assert out_p["clip_fraction"] > 0  # the comparison covers clipped steps
    if beta is not None:
        assert float(out_g["loss_kl"].detach()) == 0.0
    for g_grpo, g_ppo in zip(
        grads(total_loss(out_g), actor), grads(total_loss(out_p), actor), strict=True
    ):
        torch.testing.assert_close(g_grpo, g_ppo)


def test_matches_clip_ppo_ess_on_a_flat_batch():
    # ClipPPOLoss reduces its ESS over the first batch dimension only
    actor = categorical_actor()
    td = branch_batch(actor, (2, 3, 4)).reshape(-1)
    out_g = GRPOLoss(actor)(td.clone())
    out_p = ClipPPOLoss(actor, None, critic_coeff=None)(td.clone())
    torch.testing.assert_close(out_g["ESS"], out_p["ESS"])


def test_matches_clip_ppo_with_mask():
    actor = categorical_actor()
    td = branch_batch(actor, (3, 4, 6), masked=True)
    assert not td["mask"].all()
    grpo = GRPOLoss(actor)
    ppo = ClipPPOLoss(actor, None, critic_coeff=None)
    ppo.loss_mask_key = "mask"
    out_g, out_p = grpo(td.clone()), ppo(td.clone())
    for key in ["loss_objective", "loss_entropy"]:
        torch.testing.assert_close(out_g[key], out_p[key], msg=key)
    for g_grpo, g_ppo in zip(
        grads(total_loss(out_g), actor), grads(total_loss(out_p), actor), strict=True
    ):
        torch.testing.assert_close(g_grpo, g_ppo)


# ------------------------------------------------------------ gradient rule
RATIOS = [0.5, 0.75, 0.85, 1.0, 1.15, 1.25, 1.5, 4.0]


def ratio_batch(ratios: list[float], advantages: list[float]) -> tuple[TensorDict, object]:
    """One table row per step, uniform policy: the ratio of step i is exactly ``ratios[i]``."""
    n = len(ratios)
    actor = table_actor(n)
    log_p = math.log(1.0 / 3.0)
    td = TensorDict(
        {
            "state": torch.arange(n),
            "action": torch.zeros(n, dtype=torch.long),
            "action_log_prob": log_p - torch.tensor(ratios).log(),
            "advantage": torch.tensor(advantages).unsqueeze(-1),
            "mask": torch.ones(n, dtype=torch.bool),
        },
        batch_size=[n],
    )
    return td, actor


@pytest.mark.parametrize("clip", [0.2, (0.1, 0.3)])
@pytest.mark.parametrize("dual_clip", [None, 3.0])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_clipped_steps_get_exactly_zero_gradient(clip, dual_clip, sign):
    low, high = (clip, clip) if isinstance(clip, float) else clip
    td, actor = ratio_batch(RATIOS, [sign] * len(RATIOS))
    loss = GRPOLoss(actor, clip_epsilon=clip, dual_clip=dual_clip, entropy_bonus=False)
    total_loss(loss(td)).backward()
    grad = actor.module[0].module.table.grad
    for i, r in enumerate(RATIOS):
        # PPO: the min picks the clipped term, which is constant, when the ratio
        # left the trust region in the direction the advantage pushes it
        clipped = (sign > 0 and r > 1 + high) or (sign < 0 and r < 1 - low)
        dual = dual_clip is not None and sign < 0 and r > dual_clip
        zero = bool((grad[i] == 0).all())
        assert zero == (clipped or dual), (i, r, grad[i])


def test_dual_clip_caps_negative_advantage_loss():
    td, actor = ratio_batch([4.0, 4.0], [-1.0, 1.0])
    plain = GRPOLoss(actor, entropy_bonus=False, aggregation="dr_grpo", max_steps=1)
    dual = GRPOLoss(actor, entropy_bonus=False, dual_clip=3.0, aggregation="dr_grpo", max_steps=1)
    td["group_id"] = torch.zeros(2, dtype=torch.long)
    td["branch"] = torch.arange(2)
    # sums: -(-4) + -(1.2) without dual clip; -(-3) + -(1.2) with c = 3
    torch.testing.assert_close(plain(td)["loss_objective"], torch.tensor((4.0 - 1.2) / 2))
    torch.testing.assert_close(dual(td)["loss_objective"], torch.tensor((3.0 - 1.2) / 2))


# ---------------------------------------------------- hand-computed aggregation
def hand_batch() -> tuple[TensorDict, object]:
    """Two branches of one root, 3 steps; branch 1 ends after one step.

    Ratios and advantages (valid steps): branch 0: (1.0, 1), (1.1, -1), (1.5, 1);
    branch 1: (1.05, 0.5). Per-step losses: -1, 1.1, -1.2 (clipped at 1.2), -0.525.
    """
    actor = table_actor(6)
    log_p = math.log(1.0 / 3.0)
    ratios = torch.tensor([[1.0, 1.1, 1.5], [1.05, 1.0, 1.0]])
    lp = log_p - ratios.log()
    lp[1, 1:] = float("nan")  # masked: never read
    adv = torch.tensor([[1.0, -1.0, 1.0], [0.5, float("nan"), float("nan")]])
    td = TensorDict(
        {
            "state": torch.arange(6).view(2, 3),
            "action": torch.zeros(2, 3, dtype=torch.long),
            "action_log_prob": lp,
            "advantage": adv.unsqueeze(-1),
            "mask": torch.tensor([[True, True, True], [True, False, False]]),
            "group_id": torch.zeros(2, 3, dtype=torch.long),
            "branch": torch.tensor([[0, 0, 0], [1, 1, 1]]),
        },
        batch_size=[2, 3],
    )
    return td, actor


@pytest.mark.parametrize(
    "aggregation,max_steps,expected",
    [
        ("dapo", None, (-1.1 - 0.525) / 4),
        ("bnpo", None, (-1.1 - 0.525) / 4),
        ("token_mean", None, (-1.1 - 0.525) / 4),
        ("grpo", None, (-1.1 / 3 - 0.525) / 2),
        ("prompt_mean", None, (-1.1 / 3 - 0.525) / 2),
        ("dr_grpo", None, (-1.1 - 0.525) / (2 * 3)),
        ("dr_grpo", 10, (-1.1 - 0.525) / (2 * 10)),
    ],
)
@pytest.mark.parametrize("flat", [False, True])
def test_hand_computed_aggregations(aggregation, max_steps, expected, flat):
    td, actor = hand_batch()
    if flat:
        td = td.reshape(-1)
        if aggregation == "dr_grpo" and max_steps is None:
            max_steps = 3  # a flat batch has no time dimension to default to
    loss = GRPOLoss(actor, aggregation=aggregation, max_steps=max_steps, entropy_bonus=False)
    out = loss(td)
    torch.testing.assert_close(out["loss_objective"], torch.tensor(expected))
    torch.testing.assert_close(out["clip_fraction"], torch.tensor(0.25))
    torch.testing.assert_close(out["min_ratio"], torch.tensor(1.0))
    torch.testing.assert_close(out["max_ratio"], torch.tensor(1.5))
    torch.testing.assert_close(out["mean_ratio"], torch.tensor((1.0 + 1.1 + 1.5 + 1.05) / 4))
    log_r = torch.tensor([1.0, 1.1, 1.5, 1.05]).log()
    torch.testing.assert_close(out["kl_approx"], -log_r.mean())
    ess = log_r.exp().sum() ** 2 / log_r.exp().square().sum() / 4
    torch.testing.assert_close(out["ESS"], ess)
    adv = torch.tensor([1.0, -1.0, 1.0, 0.5])
    torch.testing.assert_close(out["advantage_mean"], adv.mean())
    torch.testing.assert_close(out["advantage_std"], adv.std(correction=0))
    assert all(torch.isfinite(v).all() for v in out.values())


@pytest.mark.parametrize("aggregation", ["grpo", "dr_grpo"])
def test_fully_masked_rows_are_not_trajectories(aggregation):
    td, actor = hand_batch()
    loss = GRPOLoss(actor, aggregation=aggregation, entropy_bonus=False)
    expected = loss(td.clone())["loss_objective"]
    padded = torch.cat([td, td[:1].apply(lambda x: x.clone())], 0)
    padded["mask"][2] = False
    padded["state"][2] = 0  # the table actor has 6 rows
    torch.testing.assert_close(loss(padded)["loss_objective"], expected)


def test_entropy_aggregated_like_the_objective():
    td, actor = hand_batch()
    out = GRPOLoss(actor, aggregation="grpo", entropy_coeff=0.1)(td)
    # uniform policy over three actions: entropy log 3 at every step
    torch.testing.assert_close(out["entropy"], torch.tensor(math.log(3.0)))
    torch.testing.assert_close(out["loss_entropy"], torch.tensor(-0.1 * math.log(3.0)))


def test_masked_garbage_observations_do_not_reach_gradients():
    actor = categorical_actor()
    td = branch_batch(actor, (2, 3, 5), masked=True)
    td["observation"][~td["mask"]] = float("nan")
    td["action_log_prob"][~td["mask"]] = float("nan")
    out = GRPOLoss(actor, aggregation="grpo", kl_to_ref_coeff=0.1)(td)
    assert all(torch.isfinite(v).all() for v in out.values())
    assert all(torch.isfinite(g).all() for g in grads(total_loss(out), actor))


# ------------------------------------------------------------ KL to reference
def perturbed(loss: GRPOLoss, scale: float = 0.3) -> None:
    with torch.no_grad():
        gen = torch.Generator().manual_seed(3)
        loss.actor_network_params.apply(
            lambda p: p.add_(scale * torch.randn(p.shape, generator=gen))
        )


@pytest.mark.parametrize("kind", ["categorical", "independent_normal", "tanh_normal"])
@pytest.mark.parametrize("estimator", ["k1", "k2", "k3", "analytic"])
def test_kl_term_against_an_independent_reference(kind, estimator):
    actor = make_actor(kind)
    reference = copy.deepcopy(actor)
    td = branch_batch(actor, (2, 3, 4))
    loss = GRPOLoss(actor, kl_to_ref_coeff=0.5, kl_estimator=estimator, entropy_bonus=False)
    out0 = loss(td.clone())
    torch.testing.assert_close(out0["loss_kl"], torch.tensor(0.0))
    perturbed(loss)
    out = loss(td.clone())
    with torch.no_grad():
        ref_dist = reference.get_dist(td)
        dist = actor.get_dist(td)  # the actor shares the (perturbed) parameters
        if estimator == "analytic":
            kl = torch.distributions.kl_divergence(dist, ref_dist)
        else:
            log_r = ref_dist.log_prob(td["action"]) - dist.log_prob(td["action"])
            kl = {"k1": -log_r, "k2": 0.5 * log_r**2, "k3": log_r.exp() - 1 - log_r}[estimator]
    torch.testing.assert_close(out["kl_to_ref"], kl.mean())
    torch.testing.assert_close(out["loss_kl"], 0.5 * kl.mean())
    assert out["kl_to_ref"] != 0
    assert all(torch.isfinite(g).all() for g in grads(out["loss_kl"], actor))


def test_stored_reference_log_prob_is_used():
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3))
    td["ref_log_prob"] = td["action_log_prob"] - 0.2
    out = GRPOLoss(actor, kl_to_ref_coeff=1.0, kl_estimator="k1", entropy_bonus=False)(td)
    with torch.no_grad():
        log_p = actor.get_dist(td).log_prob(td["action"])
    torch.testing.assert_close(out["kl_to_ref"], (log_p - td["ref_log_prob"]).mean())


def test_normal_per_dimension_log_probs_are_summed():
    # torch's Normal gives per-dimension log-probs; IndependentNormal sums them
    independent = continuous_actor("independent_normal")
    normal = continuous_actor("normal")
    normal.load_state_dict(independent.state_dict())
    td = branch_batch(independent, (2, 2, 3))
    td_normal = td.clone()
    td_normal["action_log_prob"] = td["action_log_prob"].unsqueeze(-1).expand(2, 2, 3, 2) / 2
    out_i = GRPOLoss(independent)(td)
    out_n = GRPOLoss(normal)(td_normal)
    for key in ("loss_objective", "loss_entropy", "kl_approx"):
        torch.testing.assert_close(out_i[key], out_n[key], msg=key)


def test_tanh_normal_monte_carlo_entropy():
    actor = continuous_actor("tanh_normal")
    td = branch_batch(actor, (2, 3, 4))
    out = GRPOLoss(actor, samples_mc_entropy=4)(td)
    assert torch.isfinite(out["entropy"]) and out["loss_entropy"].requires_grad


# ------------------------------------------------------------ keys and errors
def test_out_keys_match_the_output():
    actor = categorical_actor()
    td = branch_batch(actor, (2, 2, 3))
    for kwargs in ({}, {"kl_to_ref_coeff": 0.1}, {"entropy_bonus": False}):
        loss = GRPOLoss(actor, **kwargs)
        assert set(loss(td.clone()).keys()) == set(loss.out_keys)
    assert "loss_kl" not in GRPOLoss(actor).out_keys


def test_default_log_prob_key_follows_the_actor():
    actor = categorical_actor()
    assert GRPOLoss(actor).tensor_keys.sample_log_prob == actor.log_prob_keys[0]


def test_set_keys_rejects_unknown_and_renames():
    actor = categorical_actor()
    loss = GRPOLoss(actor)
    with pytest.raises(ValueError, match="not an accepted"):
        loss.set_keys(log_prob="x")
    td = branch_batch(actor, (2, 2, 3))
    expected = loss(td.clone())["loss_objective"]
    td.rename_key_("action_log_prob", "sample_log_prob")
    with pytest.raises(ValueError, match=r"'action_log_prob'.*set_keys\(sample_log_prob"):
        loss(td.clone())
    td.rename_key_("mask", "valid")
    loss.set_keys(sample_log_prob="sample_log_prob", mask="valid")
    assert "sample_log_prob" in loss.in_keys and "valid" in loss.in_keys
    torch.testing.assert_close(loss(td)["loss_objective"], expected)
