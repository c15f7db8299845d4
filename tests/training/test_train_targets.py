"""End-to-end runs whose groups carry per-action targets: distillation, regression, a crash head."""

from __future__ import annotations

import contextlib

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from train_helpers import LAB, REPLAY, csv_scalars, logged_ratios, train_run
from train_setup import TINY, compose_config

from torchrl_grpo.modules import CrashHead, PolicyEnsemble
from torchrl_grpo.modules.ensemble import member_halves
from torchrl_grpo.modules.forward_sharing import shared_forward, shared_networks
from torchrl_grpo.objectives import HorizonBootstrap
from torchrl_grpo.objectives.survival import TailSurvival
from torchrl_grpo.training import Trainer
from torchrl_grpo.training.algos.branch_tails import crash_labels


def test_regression_stores_each_rows_advantage_and_trains_on_it(tmp_path):
    overrides = [
        *REPLAY,
        "algo.group_fit_coeff=0.5",
        "algo.group_fit_loss=regression",
        "algo.group_fit_temperature=1.0",
        "algo.action_weights=policy",
        "logger=csv",
    ]
    trainer = train_run(tmp_path, "regression", [*overrides, "experiment.total_frames=60"])
    stored = trainer.algo.replay[:]
    # The target is the group's advantage, not the surrogate's policy-weighted one.
    torch.testing.assert_close(stored["distill_target"], stored["advantage"])
    assert bool((stored["distill_weight"] == 1).all())
    assert bool((stored["advantage"].reshape(-1, 5).sum(-1).abs() < 1e-4).all())  # centred
    scalars = csv_scalars(tmp_path / "regression")
    ratios = logged_ratios(scalars, "train/loss_distill", "train/distill_squared_error")
    assert ratios == pytest.approx([0.5] * trainer.iteration)
    # Its replay holds regression targets: a resume with the cross-entropy is refused.
    resume = f"resume={tmp_path / 'regression' / 'last.pt'}"
    other = compose_config(
        [*TINY, *REPLAY, resume, "algo.group_fit_coeff=0.5", "algo.group_fit_loss=cross_entropy"]
    )
    with pytest.raises(ValueError, match="group_fit_loss=regression targets.*cross_entropy"):
        Trainer(other, run_dir=tmp_path / "other")


def test_a_crash_head_learns_from_each_branchs_crash(tmp_path):
    overrides = [*REPLAY, "model.crash_head=true", "algo.crash_head_coeff=0.5", "logger=csv"]
    overrides += ["algo.tail_policy=idle", "rollout.horizon=4", "experiment.total_frames=120"]
    trainer = train_run(tmp_path, "crash_head", overrides)
    stored = trainer.algo.replay[:]
    # One label per enumerated action; with the idle tail some actions crash, some do not.
    crashed = stored["branch_crashed"].reshape(-1, 5)
    assert stored["branch_crashed"].dtype == torch.bool
    assert bool(crashed.any()) and not bool(crashed.all())
    scalars = csv_scalars(tmp_path / "crash_head")
    ratios = logged_ratios(scalars, "train/loss_crash_head", "train/crash_head_bce")
    assert ratios == pytest.approx([0.5] * trainer.iteration)
    for refused, match in (
        (["algo=ppo"], "model.crash_head is trained.*algo=ppo"),
        (
            [*LAB, "algo.explore_steps=2", "algo.group_fit_coeff=0"],
            "model.crash_head learns.*explore_steps=1",
        ),
    ):
        cfg = compose_config([*TINY, "model.crash_head=true", *refused])
        with pytest.raises(ValueError, match=match):
            Trainer(cfg, run_dir=tmp_path / "refused")


def test_a_survival_bootstrap_asks_the_crash_head_at_each_branchs_end(tmp_path):
    overrides = [*REPLAY, "model.crash_head=true", "algo.bootstrap=survival", "logger=csv"]
    overrides += ["algo.tail_policy=idle", "rollout.horizon=4", "experiment.total_frames=120"]
    trainer = train_run(tmp_path, "survival", overrides)
    survival = csv_scalars(tmp_path / "survival")["train/tail_survival_mean"]
    assert len(survival) == trainer.iteration
    assert all(0 < p < 1 for p in survival)
    assert trainer.algo.tail_survival.head is trainer.algo.crash_head.head
    cfg = compose_config([*TINY, *REPLAY, "algo.bootstrap=survival", "model.crash_head=false"])
    with pytest.raises(ValueError, match="algo.bootstrap=survival.*model.crash_head=true"):
        Trainer(cfg, run_dir=tmp_path / "refused")


def test_the_survival_bootstrap_bootstraps_the_crash_labels_even_with_crash_label_branch(
    tmp_path,
):
    # What the code does, and experiment=best's teachers were trained with: the survival
    # estimate that algo.bootstrap=survival builds also labels the head's rows of branches
    # the horizon cut alive, whatever algo.crash_label says (docs/experimental.md). A
    # change of this is a change of the teachers' recipe: make it deliberately.
    overrides = [*REPLAY, "model.crash_head=true", "algo.bootstrap=survival"]
    overrides += ["algo.crash_label=branch", "algo.tail_policy=idle", "rollout.horizon=4"]
    trainer = train_run(tmp_path, "survival_labels", [*overrides, "experiment.total_frames=60"])
    labels = trainer.algo.replay[:]["branch_crashed"]
    assert labels.is_floating_point()
    assert bool(((labels > 0) & (labels < 1)).any()), "only 0/1 labels: the branch's own crash"


def test_bootstrapped_crash_labels_are_the_heads_estimate_where_the_horizon_cut(tmp_path):
    # Three branches of 3 steps from roots at episode steps 2, 2 and 27 (limit 30): one
    # crashes at its second step, one is cut alive, one reaches the episode's end.
    mask = torch.tensor([[[True, True, False], [True, True, True], [True, True, True]]])
    terminated = torch.zeros(1, 3, 3, 1, dtype=torch.bool)
    terminated[0, 0, 1] = True
    batch = TensorDict(
        {
            "mask": mask,
            "root_step": torch.tensor([2, 2, 27]).reshape(1, 3, 1).expand(1, 3, 3),
            "tail_survival": torch.tensor([0.5, 0.75, 0.1]).reshape(1, 3, 1).expand(1, 3, 3),
            ("next", "terminated"): terminated,
        },
        batch_size=[1, 3, 3],
    )
    survival = TailSurvival(CrashHead(nn.Linear(1, 4), 2))
    labels = crash_labels(batch, HorizonBootstrap(30), survival)
    assert labels.tolist() == [[[1.0] * 3, [0.25] * 3, [0.0] * 3]]
    # Without the survival module: whether each branch crashed.
    assert crash_labels(batch, HorizonBootstrap(30), None).tolist() == [
        [[True] * 3, [False] * 3, [False] * 3]
    ]
    # End to end, with the batch-mean bootstrap: the head's estimate is asked for the
    # labels alone, and the refusal without a head names the option.
    overrides = [*REPLAY, "model.crash_head=true", "algo.crash_label=bootstrap", "logger=csv"]
    overrides += ["algo.tail_policy=idle", "rollout.horizon=4", "experiment.total_frames=120"]
    trainer = train_run(tmp_path, "labels", overrides)
    assert str(trainer.cfg.algo.bootstrap) == "batch_mean"
    assert trainer.algo.tail_survival.head is trainer.algo.crash_head.head
    scalars = csv_scalars(tmp_path / "labels")
    assert len(scalars["train/crash_head_bce"]) == trainer.iteration
    assert len(scalars["train/tail_survival_mean"]) == trainer.iteration
    cfg = compose_config([*TINY, *REPLAY, "algo.crash_label=bootstrap", "model.crash_head=false"])
    with pytest.raises(ValueError, match="algo.crash_label=bootstrap.*model.crash_head=true"):
        Trainer(cfg, run_dir=tmp_path / "refused")


def ensemble_run(tmp_path, name: str, extra: list[str]) -> tuple:
    """A tiny run of two members with a crash head and the regression: algo, ensemble, replay."""
    overrides = [*REPLAY, "model.crash_head=true", "model.ensemble=2", "algo.group_fit_coeff=1"]
    overrides += ["algo.group_fit_loss=regression", "algo.group_fit_temperature=1", *extra]
    algo = train_run(tmp_path, name, [*overrides, "experiment.total_frames=60"]).algo
    [ensemble] = [m for m in algo.policy.modules() if isinstance(m, PolicyEnsemble)]
    return algo, ensemble, algo.current_log_probs(algo.replay[:])


def test_each_member_of_an_ensemble_learns_from_its_own_outputs(tmp_path):
    algo, ensemble, batch = ensemble_run(tmp_path, "ensemble", [])
    first, second = ensemble.members
    # Each member's ratio is taken around its own log-probs.
    for member in range(2):
        with ensemble.acting(member):
            own = algo.policy.get_dist(batch.select("observation")).log_prob(batch["action"])
        torch.testing.assert_close(batch["member_action_log_prob"][:, member], own)

    def first_grads(terms) -> list[torch.Tensor]:
        algo.optimizer.zero_grad(set_to_none=False)
        out = terms(batch)
        assert {"loss_objective", "loss_distill", "loss_crash_head"} <= set(out.keys())
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        return [p.grad.clone() for p in first.parameters()]

    shared = first_grads(algo.member_terms)
    with ensemble.acting(0):
        alone = first_grads(algo.loss_terms)
    # The ensemble's loss is the mean of the members' own losses: half of member 0's.
    for mixed, own in zip(shared, alone, strict=True):
        torch.testing.assert_close(mixed, own / 2)
    assert any(bool(g.abs().sum() > 0) for g in shared)
    # Member 0's gradient does not depend on member 1 (a fit of the mean logits would).
    with torch.no_grad():
        for p in second.parameters():
            p.add_(torch.randn_like(p))
    for before, after in zip(shared, first_grads(algo.member_terms), strict=True):
        torch.testing.assert_close(before, after)
    # The members started apart and both trained; the policy acts with their mean.
    assert not torch.equal(next(first.parameters()), next(second.parameters()))
    obs = batch["observation"][:3]
    torch.testing.assert_close(ensemble(obs), (first(obs) + second(obs)) / 2)
    with pytest.raises(ValueError, match="model.ensemble must be >= 1"):
        Trainer(compose_config([*TINY, *LAB, "model.ensemble=0"]), run_dir=tmp_path / "refused")


def test_bagged_members_learn_from_their_own_half_of_the_groups(tmp_path):
    algo, ensemble, batch = ensemble_run(tmp_path, "bagged", ["model.bagging=true"])
    halves = member_halves(batch["group_id"], 2)
    assert bool(halves.all(-1).any()) and not bool(halves.all())  # some groups train one

    def member_grads(terms, data, member: int) -> list[torch.Tensor]:
        algo.optimizer.zero_grad(set_to_none=False)
        out = terms(data)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        return [p.grad.clone() for p in ensemble.members[member].parameters()]

    for member in range(2):
        bagged = member_grads(algo.member_terms, batch, member)
        with ensemble.acting(member):
            own = member_grads(algo.loss_terms, batch[halves[:, member]], member)
        # Each member's gradient is that of its own groups' loss, halved by the mean.
        for mixed, alone in zip(bagged, own, strict=True):
            torch.testing.assert_close(mixed, alone / 2)
    for refused in ([*LAB, "model.ensemble=1"], ["model=lab", "algo=ppo"]):
        cfg = compose_config([*TINY, "model.ensemble=2", "model.bagging=true", *refused])
        with pytest.raises(ValueError, match="model.bagging gives each ensemble member"):
            Trainer(cfg, run_dir=tmp_path / "refused")


def test_the_losses_of_a_minibatch_run_the_network_once(tmp_path):
    overrides = [*REPLAY, "model.crash_head=true", "algo.group_fit_coeff=1"]
    overrides += ["algo.group_fit_loss=regression", "algo.group_fit_temperature=1"]
    trainer = train_run(tmp_path, "shared", [*overrides, "experiment.total_frames=60"])
    algo = trainer.algo
    [net] = shared_networks(algo.policy)
    runs: list[int] = []
    layer = next(m for m in net.modules() if isinstance(m, nn.Linear))
    layer.register_forward_hook(lambda *args: runs.append(1))
    batch = algo.current_log_probs(algo.replay[:])

    def terms(shared: bool) -> tuple[TensorDict, int, list[torch.Tensor]]:
        algo.optimizer.zero_grad(set_to_none=False)
        runs.clear()
        with shared_forward(algo.policy) if shared else contextlib.nullcontext():
            out = algo.member_terms(batch)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        return out, len(runs), [p.grad.clone() for p in algo.policy.parameters()]

    separate, separate_runs, separate_grads = terms(False)
    shared, shared_runs, shared_grads = terms(True)
    # The surrogate, the regression and the crash head: three runs, or one shared.
    assert {"loss_objective", "loss_distill", "loss_crash_head"} <= set(shared.keys())
    assert (separate_runs, shared_runs) == (3, 1)
    for key in separate.keys():
        torch.testing.assert_close(shared[key], separate[key], rtol=0, atol=0)
    for a, b in zip(separate_grads, shared_grads, strict=True):
        torch.testing.assert_close(a, b)
    runs.clear()
    stats = algo.optimise(batch)  # what training does: one run per minibatch
    assert len(runs) == stats["train/minibatches"] > 0


def test_merges_recipe_fits_each_roots_expected_regret(tmp_path):
    # env=merge alone: the regret fit over groups scored under always-SLOWER, as measured
    # (docs/results.md, section 5); a shorter horizon and replay keep it small.
    overrides = ["env=merge", "env.backend=tensor", "rollout.horizon=4", "algo.replay_groups=50"]
    overrides += ["logger=csv", "experiment.total_frames=120"]
    trainer = train_run(tmp_path, "merge", overrides)
    assert type(trainer.algo.distill).__name__ == "GroupRegretLoss"
    stored = trainer.algo.replay[:]
    advantage = stored["advantage"].reshape(-1, 5)
    regret = advantage.max(-1, keepdim=True).values - advantage
    torch.testing.assert_close(stored["distill_target"].reshape(-1, 5), regret)
    best = (regret == 0).float()
    weight = best / best.sum(-1, keepdim=True)
    torch.testing.assert_close(stored["distill_weight"].reshape(-1, 5), weight)
    scalars = csv_scalars(tmp_path / "merge")
    expected = scalars["train/distill_expected_regret"]
    assert len(expected) == trainer.iteration and all(v >= 0 for v in expected)
    # loss_distill = coeff (1) * (expected regret + ANCHOR * cross-entropy): never below it.
    assert all(total >= v for total, v in zip(scalars["train/loss_distill"], expected, strict=True))
