"""End-to-end runs on tiny budgets: the smoke run, exact resume, Ctrl-C."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor
from train_helpers import LAB, REPLAY, csv_scalars, train_run
from train_setup import ROOT, TINY, compose_config, run_script

from torchrl_grpo.modules.greedy_tail import EXPLORED
from torchrl_grpo.modules.scripted.actions import SLOWER
from torchrl_grpo.objectives import GRPOLoss
from torchrl_grpo.training import Trainer, load_checkpoint
from torchrl_grpo.training.algos.grpo import policy_weighted
from torchrl_grpo.training.checkpoint import changed_keys
from torchrl_grpo.training.collect import make_collector
from torchrl_grpo.training.env_builder import make_rollout_env


def test_smoke_run_writes_finite_metrics_and_checkpoint(smoke_run):
    proc, run_dir, elapsed = smoke_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    # The script ends by telling where everything is.
    for label in ("run folder:", "checkpoint:", "logs:", "results:", "curve:"):
        assert label in proc.stdout, proc.stdout
    scalars = csv_scalars(run_dir)
    for name in (
        "collect/crash_rate",
        "collect/group_return_mean",
        "collect/group_return_std",
        "train/advantage_mean",
        "train/loss_objective",
        "train/loss_entropy",
        "train/loss_kl",
        "train/clip_fraction",
        "train/ESS",
        "train/kl_approx",
        "train/entropy",
        "time/collect",
        "time/update",
        "time/fps",
        "eval/return",
        "eval/crash_rate",
        "eval/speed",
        "eval/length",
        "eval/final_return",
    ):
        assert scalars.get(name), f"no {name} metric in {sorted(scalars)}"
        assert all(math.isfinite(v) for v in scalars[name]), (name, scalars[name])
    assert scalars["collect/frames"][-1] >= 200
    ckpt = load_checkpoint(run_dir / "last.pt")
    assert ckpt["frames"] >= 200 and ckpt["iteration"] >= 2
    params = list(ckpt["policy"].values())
    assert params and all(torch.isfinite(p).all() for p in params)
    assert (run_dir / "results.md").read_text().count("|") > 10
    assert list((run_dir / "plots").glob("group_it*.png"))
    # Every evaluation records the training wall-clock it was at: growing, within the run.
    history = (run_dir / "eval_history.jsonl").read_text().splitlines()
    walls = [json.loads(line)["wall_seconds"] for line in history]
    # The first is the evaluation before the first batch: no training yet.
    assert len(walls) > 1 and walls[0] == 0 and walls[1] > 0 and walls == sorted(walls), walls
    assert walls[-1] < elapsed


def test_evaluate_refuses_an_env_beside_a_checkpoint(tmp_path, smoke_run):
    # Here, beside the other reader of the shared smoke run: a test worker trains it once.
    _, run_dir, _ = smoke_run
    proc = run_script(
        "evaluate.py",
        [f"checkpoint={run_dir / 'last.pt'}", "env=merge", "hydra.run.dir=h"],
        timeout=180,
        cwd=tmp_path,
    )
    assert proc.returncode != 0
    assert "env=merge: a checkpoint is evaluated on its own env" in proc.stderr


def _params(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in trainer.algo.loss.state_dict().items()}


@pytest.mark.parametrize(
    "algo,extra,first,total",
    [
        pytest.param(
            "grpo_branch",
            ["algo.group_size=2", "rollout.decision_interval=2"],
            40,
            110,
            marks=pytest.mark.slow,  # grpo_branch_replay resumes the same loop and more
        ),
        ("ppo", ["rollout.frames_per_batch=32"], 32, 96),
        pytest.param("grpo_branch", [*REPLAY], 60, 160, marks=pytest.mark.slow),  # 12 s
    ],
    ids=["grpo_branch", "ppo", "grpo_branch_replay"],
)
def test_resume_continues_exactly(tmp_path, algo, extra, first, total):
    common = [f"algo={algo}", "experiment.checkpoint_every=1", *extra]
    straight = train_run(tmp_path, "straight", [*common, f"experiment.total_frames={total}"])
    stopped = train_run(tmp_path, "stopped", [*common, f"experiment.total_frames={first}"])
    assert 0 < stopped.frames < straight.frames
    resumed = train_run(
        tmp_path,
        "resumed",
        [*common, f"experiment.total_frames={total}", f"resume={tmp_path / 'stopped' / 'last.pt'}"],
    )
    assert (resumed.iteration, resumed.frames) == (straight.iteration, straight.frames)
    a, b = _params(straight), _params(resumed)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # The control: the stopped run's parameters differ, so the check can fail.
    c = _params(stopped)
    assert any(not torch.equal(a[k], c[k]) for k in a)


def test_a_scripted_tail_scores_every_first_action_from_the_learners_trunks(tmp_path):
    overrides = [
        *LAB,
        "algo.group_size=5",
        "rollout.horizon=3",
        "algo.explore_steps=1",
        "algo.first_action=enumerate",
        "algo.trunk=greedy",
        "algo.tail_policy=slower",
        "algo.tail_learner_steps=0",  # the base policy right after the first action
    ]
    trainer = train_run(tmp_path, "base_tail", [*overrides, "experiment.total_frames=40"])
    assert trainer.iteration >= 1
    cfg = trainer.cfg
    env = make_rollout_env(cfg.env, cfg.rollout, snapshots=True)
    collector = make_collector(
        cfg, env, trainer.policy, seed=0, tail_policy=trainer.algo.tail_policy
    )
    try:
        batch = next(iter(collector))
        assert collector.root_source.policy is trainer.policy  # trunks: the learner, not the base
    finally:
        collector.shutdown()
    first = batch["action"][..., 0]
    assert (first == torch.arange(5)).all()
    tail = batch["mask"] & ~batch[EXPLORED]
    assert bool(tail[..., 1:].any()) and not bool(tail[..., 0].any())
    assert (batch["action"][tail] == SLOWER).all()


def test_replayed_groups_accumulate_and_get_the_current_policys_log_probs(tmp_path):
    trainer = train_run(tmp_path, "replay", [*REPLAY, "experiment.total_frames=60"])
    rows = len(trainer.algo.replay)
    assert trainer.iteration >= 2 and rows > 5  # more than one batch's rows
    old = trainer.algo.replay[:]
    fresh = old[:3].clone()
    fresh["action_log_prob"] = torch.zeros(3)  # a stale value, overwritten
    data = trainer.algo.replayed(fresh)
    assert data.shape[0] == rows + 3
    logits = trainer.policy.module[0](data.select("observation").clone())["logits"]
    expected = torch.log_softmax(logits, -1).gather(-1, data["action"].unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(data["action_log_prob"], expected)
    # FIFO: 50 groups of 5 branches, one trained step each.
    trainer.algo.replay.extend(torch.cat([old] * (300 // rows + 1)))
    assert len(trainer.algo.replay) == 250
    # A resume with another replay size is refused when it loads, not mid-run.
    bigger = [*REPLAY, "algo.replay_groups=60", f"resume={tmp_path / 'replay' / 'last.pt'}"]
    with pytest.raises(ValueError, match="algo.replay_groups"):
        Trainer(compose_config([*TINY, *bigger]), run_dir=tmp_path / "bigger")


def test_policy_weights_scale_advantages_by_n_pi_and_leave_the_replay_alone(tmp_path):
    overrides = [*REPLAY, "algo.action_weights=policy", "experiment.total_frames=60"]
    trainer = train_run(tmp_path, "weighted", overrides)
    stored = trainer.algo.replay[:].clone()
    data = policy_weighted(trainer.algo.replayed(stored[:1].clone()), 5)
    plain = torch.cat([stored["advantage"], stored["advantage"][:1]])
    logits = trainer.policy.module[0](data.select("observation").clone())["logits"]
    prob = torch.softmax(logits, -1).gather(-1, data["action"].unsqueeze(-1))
    torch.testing.assert_close(data["advantage"], plain * 5 * prob)
    assert torch.equal(trainer.algo.replay[:]["advantage"], plain)  # stored unweighted


def test_policy_weights_give_the_expected_surrogates_gradient():
    """Against autograd of ``sum_a pi(a|s) A(s, a)``, the all-action policy gradient."""
    n_states, n_actions = 3, 5
    table = torch.nn.Parameter(torch.randn(n_states, n_actions))
    actor = ProbabilisticActor(
        TensorDictModule(lambda state: table[state], ["state"], ["logits"]),
        ["logits"],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )
    advantage = torch.randn(n_states, n_actions)
    log_pi = torch.log_softmax(table.detach(), -1)
    data = TensorDict(
        {
            "state": torch.arange(n_states).repeat_interleave(n_actions),
            "action": torch.arange(n_actions).repeat(n_states),
            "action_log_prob": log_pi.reshape(-1),
            "advantage": advantage.reshape(-1, 1),
            "mask": torch.ones(n_states * n_actions, dtype=torch.bool),
        },
        batch_size=[n_states * n_actions],
    )
    loss = GRPOLoss(actor, entropy_bonus=False)
    loss(policy_weighted(data, n_actions))["loss_objective"].backward()
    reference = table.detach().clone().requires_grad_(True)
    expected = -(torch.softmax(reference, -1) * advantage).sum() * n_actions / data.numel()
    expected.backward()
    torch.testing.assert_close(table.grad, reference.grad)
    # The control: uniform weights give another gradient.
    table.grad = None
    loss(data)["loss_objective"].backward()
    assert not torch.allclose(table.grad, reference.grad)


def test_resume_refuses_another_algorithm_or_model(tmp_path):
    train_run(tmp_path, "grpo", ["experiment.total_frames=20"])
    resume = f"resume={tmp_path / 'grpo' / 'last.pt'}"
    with pytest.raises(ValueError, match="algo=grpo_branch"):
        compose_config([*TINY, "algo=ppo", resume])
    with pytest.raises(ValueError, match="algo=grpo_branch, not algo=grpo_lab"):
        compose_config([*TINY, *LAB, resume])  # the lab's GRPO is another algorithm
    with pytest.raises(ValueError, match="model.kind='scene', not 'mlp'"):
        compose_config([*TINY, "model=mlp", resume])
    # The Trainer checks as well, for configs composed elsewhere.
    cfg = compose_config([*TINY, resume])
    cfg.model.num_cells = [16]
    with pytest.raises(ValueError, match=r"model.num_cells=\[32\], not \[16\]"):
        Trainer(cfg, run_dir=tmp_path / "cells")
    # The run's own model resumes.
    Trainer(compose_config([*TINY, resume]), run_dir=tmp_path / "same")


def test_changed_keys_compares_only_keys_both_configs_hold():
    saved = {"kind": "mlp", "cells": [64], "sub": {"a": 1, "old": 2}}
    current = {"kind": "mlp", "cells": [32], "sub": {"a": 3}, "prior": None}
    # "old" left the schema and "prior" joined it: neither is a change of this run.
    assert changed_keys(saved, current) == {"cells": ([64], [32]), "sub.a": (1, 3)}
    assert changed_keys(saved, saved) == {}


@pytest.mark.slow  # 13 s: a run on two workers, interrupted
def test_ctrl_c_saves_and_leaves_no_worker(tmp_path):
    run_dir = tmp_path / "run"
    args = [
        str(ROOT / "scripts" / "train.py"),
        *TINY,
        "rollout.backend=parallel",
        "rollout.num_workers=1",
        "experiment.total_frames=100000",
        "experiment.checkpoint_every=1",
        f"experiment.out_dir={run_dir}",
    ]
    proc = subprocess.Popen(
        [sys.executable, *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "WANDB_MODE": "offline"},
    )
    try:
        deadline = time.monotonic() + 90
        while not (run_dir / "last.pt").exists():
            assert proc.poll() is None, proc.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "no checkpoint within 90 s"
            time.sleep(0.5)
        # What a terminal's Ctrl-C does: SIGINT to the whole process group.
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-3000:]
    assert "interrupted" in out
    # The warning once, not once per forked worker too.
    assert (out + err).count("Ctrl-C: finishing this iteration") == 1, out + err
    ckpt = load_checkpoint(run_dir / "last.pt")
    assert 0 < ckpt["frames"] < 100000
    # Every process of the session (the trainer, its env worker, multiprocessing's
    # resource tracker) is gone, within a few seconds of the trainer's exit.
    deadline = time.monotonic() + 20
    with pytest.raises(ProcessLookupError):
        while time.monotonic() < deadline:
            os.killpg(proc.pid, 0)
            time.sleep(0.2)
