"""Teacher distillation (``algo=distill``): teachers, the loss, the kept states, a run, resume."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor
from train_setup import TINY, compose_config, visited_states

from torchrl_grpo.objectives import TeacherDistillLoss
from torchrl_grpo.training import Trainer, load_checkpoint, make_env, make_policy
from torchrl_grpo.training.algos.labelled import LabelledStates
from torchrl_grpo.training.checkpoint import save_checkpoint
from torchrl_grpo.training.config import check_config
from torchrl_grpo.training.teacher_loading import load_teachers

TENSOR = ["env.backend=tensor", "env.num_envs=32"]


@pytest.fixture(scope="module")
def teachers(tmp_path_factory):
    """Two tiny runs of other architectures: a PPO table MLP, a GRPO scene net with a crash head."""
    root = tmp_path_factory.mktemp("teachers")
    runs = {
        "mlp": ["algo=ppo", "model=mlp", "seed=1"],
        "crash": ["model.crash_head=true", "model.crash_aversion=3", "seed=2"],
    }
    for name, overrides in runs.items():
        cfg = compose_config([*TINY, *TENSOR, *overrides, "experiment.total_frames=60"])
        Trainer(cfg, run_dir=root / name).train()
    return [str(root / name / "last.pt") for name in runs]


def distill_config(teachers: list[str], extra: list[str] = ()):
    return compose_config(
        [*TINY, *TENSOR, "algo=distill", f"algo.teachers=[{','.join(teachers)}]", *extra]
    )


def test_teachers_act_with_the_mean_logits_of_each_checkpoints_own_policy(teachers):
    cfg = distill_config(teachers)
    env = make_env(cfg.env)
    states = visited_states(16)
    expected = []
    for path in teachers:  # each checkpoint's policy, built from its own config
        ckpt = load_checkpoint(path)
        policy = make_policy(OmegaConf.create(ckpt["config"]).model, env)
        policy.load_state_dict(ckpt["policy"])
        expected.append(policy(states.clone())["logits"])
    assert not torch.allclose(expected[0], expected[1])  # two different teachers
    got = load_teachers(teachers, cfg.env, env)(states.clone())["teacher_logits"]
    torch.testing.assert_close(got, (expected[0] + expected[1]) / 2)
    assert not got.requires_grad


def test_a_teacher_of_another_env_config_or_no_file_is_refused(teachers, tmp_path):
    cfg = distill_config(teachers)
    env = make_env(cfg.env)
    ckpt = load_checkpoint(teachers[0])
    ckpt["config"]["env"]["config"] = {"lanes_count": 3}
    other = save_checkpoint(ckpt, tmp_path / "other.pt")
    with pytest.raises(
        ValueError, match=r"teacher .*other.pt was trained on highway-fast-v0 with env.config"
    ):
        load_teachers([teachers[1], str(other)], cfg.env, env)
    with pytest.raises(FileNotFoundError, match="no checkpoint at .*missing.pt"):
        load_teachers([str(tmp_path / "missing.pt")], cfg.env, env)


def test_the_config_needs_teachers_a_minibatch_of_kept_states_and_a_crash_coeff(teachers):
    with pytest.raises(ValueError, match="algo=distill needs algo.teachers"):
        check_config(compose_config([*TINY, "algo=distill"]))
    with pytest.raises(ValueError, match=r"algo.replay_frames \(32\) must hold at least one"):
        check_config(distill_config(teachers, ["algo.replay_frames=32"]))
    crash = ["model.crash_head=true", "algo.crash_head_coeff=0"]
    with pytest.raises(ValueError, match="algo.crash_head_coeff must be a finite number > 0"):
        check_config(distill_config(teachers, crash))
    check_config(distill_config(teachers, crash[:1]))  # a student with a crash head
    with pytest.raises(ValueError, match="algo.crash_head_coeff must be a finite number > 0"):
        check_config(compose_config([*TINY, "algo=grpo_lab", *crash]))  # GRPO's head: the same
    # The algos with neither branch groups nor teachers still refuse one.
    with pytest.raises(ValueError, match="model.crash_head is trained on the crashes"):
        check_config(compose_config([*TINY, "algo=ppo", "model.crash_head=true"]))


def _actor(logits: torch.Tensor) -> ProbabilisticActor:
    """A policy that gives every state the logits ``logits`` (a bias, no weight)."""
    net = torch.nn.Linear(1, logits.shape[-1])
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(logits)
    module = TensorDictModule(net, ["observation"], ["logits"])
    return ProbabilisticActor(
        module, ["logits"], distribution_class=torch.distributions.Categorical
    )


def test_the_loss_is_the_kl_divergence_worked_by_hand():
    teacher = torch.tensor([[math.log(2.0), 0.0, 0.0], [0.0, 0.0, math.log(2.0)]])
    data = TensorDict(observation=torch.zeros(2, 1), teacher_logits=teacher, batch_size=[2])
    # Teacher: (1/2, 1/4, 1/4) and (1/4, 1/4, 1/2); the policy: (1/4, 1/4, 1/2) everywhere.
    loss = TeacherDistillLoss(_actor(torch.tensor([0.0, 0.0, math.log(2.0)])))
    out = loss(data).detach()
    first = 0.5 * math.log(0.5 / 0.25) + 0.25 * math.log(1.0) + 0.25 * math.log(0.25 / 0.5)
    assert float(out["loss_distill"]) == pytest.approx(first / 2, abs=1e-6)
    assert float(out["distill_agreement"]) == 0.5
    entropy = -(0.5 * math.log(0.5) + 2 * 0.25 * math.log(0.25))
    assert float(out["teacher_entropy"]) == pytest.approx(entropy, abs=1e-6)
    # Logits shifted by a constant are the same distribution: no loss, no gradient.
    same = TeacherDistillLoss(_actor(teacher[1] + 5.0))
    out = same(data[1:])
    out["loss_distill"].backward()
    assert float(out["loss_distill"]) == pytest.approx(0.0, abs=1e-6)
    assert same.actor_network.module[0].module.bias.grad.abs().max() < 1e-6


def test_the_loss_names_a_missing_key_and_a_count_of_actions_that_differs():
    loss = TeacherDistillLoss(_actor(torch.zeros(3)))
    loss.set_keys(teacher_logits="labels")
    with pytest.raises(ValueError, match="the input has no 'labels' entry"):
        loss(TensorDict(observation=torch.zeros(2, 1), batch_size=[2]))
    data = TensorDict(observation=torch.zeros(2, 1), labels=torch.zeros(2, 5), batch_size=[2])
    with pytest.raises(ValueError, match=r"the teacher has \(2, 5\) logits, the policy \(2, 3\)"):
        loss(data)


def test_kept_states_go_oldest_first_and_a_checkpoint_holds_only_those_kept():
    kept = LabelledStates(100)
    kept.extend(TensorDict(x=torch.arange(30.0), batch_size=[30]))
    state = kept.state_dict()
    assert state["rows"].shape == (30,) and state["cursor"] == 30
    for start in (30, 60, 90):
        kept.extend(TensorDict(x=torch.arange(start, start + 30.0), batch_size=[30]))
    assert sorted(kept.rows["x"].tolist()) == list(range(20, 120))
    with pytest.raises(ValueError, match="kept up to 100 states, this run 50"):
        LabelledStates(50).load_state_dict(kept.state_dict())


def test_the_student_learns_the_teachers_distribution_on_states_it_did_not_see(teachers, tmp_path):
    cfg = distill_config(
        teachers,
        ["experiment.total_frames=640", "rollout.frames_per_batch=64", "algo.max_minibatches=40"],
    )
    trainer = Trainer(cfg, run_dir=tmp_path / "student")
    held_out = visited_states(32, seed=123)
    target = trainer.algo.teachers(held_out.clone())["teacher_logits"]

    def kl_to_teacher() -> float:
        data = held_out.clone().set("teacher_logits", target)
        with torch.no_grad():
            return float(TeacherDistillLoss(trainer.policy)(data)["loss_distill"])

    before = kl_to_teacher()
    result = trainer.train()
    # Frames are the student's world steps: 10 batches of 64.
    assert (result.iterations, trainer.frames) == (10, 640)
    assert len(trainer.algo.replay) == 640
    after = kl_to_teacher()
    assert after < 0.3 * before


def test_resume_of_a_distillation_continues_exactly(teachers, tmp_path):
    common = ["experiment.checkpoint_every=1", "algo.replay_frames=200", "algo.max_minibatches=3"]

    def train(name, frames):
        cfg = distill_config(teachers, [*common, f"experiment.total_frames={frames}"])
        trainer = Trainer(cfg, run_dir=tmp_path / name)
        trainer.train()
        return trainer

    straight = train("straight", 320)
    stopped = train("stopped", 128)
    path = tmp_path / "stopped" / "last.pt"
    cfg = compose_config([f"resume={path}", "experiment.total_frames=320"])
    resumed = Trainer(cfg, run_dir=tmp_path / "resumed")
    resumed.train()
    assert (resumed.iteration, resumed.frames) == (straight.iteration, straight.frames)
    a, b, c = (t.policy.state_dict() for t in (straight, resumed, stopped))
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert any(not torch.equal(a[k], c[k]) for k in a)  # the control: it can fail
    # The kept states wrapped around (320 > 200) and are the same rows.
    assert torch.equal(
        straight.algo.replay.rows["observation"], resumed.algo.replay.rows["observation"]
    )


def test_without_a_cap_each_batch_passes_over_every_kept_state(teachers, tmp_path):
    cfg = distill_config(
        teachers,
        ["experiment.total_frames=192", "algo.max_minibatches=null", "algo.epochs=2"],
    )
    trainer = Trainer(cfg, run_dir=tmp_path / "uncapped")
    trainer.train()
    # Batches of 64 frames, minibatches of 64: 64, 128 then 192 states kept, two passes each.
    assert len(trainer.algo.replay) == 192
    assert trainer.algo.updates == 2 * (1 + 2 + 3)
