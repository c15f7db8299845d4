"""A student with a crash head (``algo=distill model.crash_head=true``): its teachers' odds."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from train_setup import TINY, compose_config, visited_states

from torchrl_grpo.modules import CrashHead
from torchrl_grpo.objectives import TeacherCrashLoss
from torchrl_grpo.training import Trainer, load_checkpoint, make_env, make_policy
from torchrl_grpo.training.checkpoint import save_checkpoint
from torchrl_grpo.training.config import check_config
from torchrl_grpo.training.teacher_loading import load_teachers

TENSOR = ["env.backend=tensor", "env.num_envs=32"]
CRASH_HEAD = ["model.crash_head=true", "model.crash_aversion=3"]
#: The scene network's output layer: 5 policy logits, then 5 crash logits.
OUTPUT_BIAS = "module.0.module.net.mlp.2.bias"


@pytest.fixture(scope="module")
def teachers(tmp_path_factory):
    """Two tiny GRPO runs with crash heads (other aversions), and a PPO run without one."""
    root = tmp_path_factory.mktemp("crash_teachers")
    runs = {
        "crash3": [*CRASH_HEAD, "seed=2"],
        "crash1": [*CRASH_HEAD[:1], "model.crash_aversion=1", "seed=4"],
        "headless": ["algo=ppo", "seed=1"],
    }
    for name, overrides in runs.items():
        cfg = compose_config([*TINY, *TENSOR, *overrides, "experiment.total_frames=60"])
        Trainer(cfg, run_dir=root / name).train()
    for name, shift in (("crash3", 3.0), ("crash1", 1.0)):
        # 60 frames leave the crash odds near a fresh network's: give the teachers odds of
        # their own, far from where a student starts.
        path = root / name / "last.pt"
        ckpt = load_checkpoint(path)
        bias = ckpt["policy"][OUTPUT_BIAS]
        bias[5:] += shift * torch.tensor([1.0, -1.0, 0.5, -0.5, 0.0])
        save_checkpoint(ckpt, path)
    return {name: str(root / name / "last.pt") for name in runs}


def student_config(paths: list[str], extra: list[str] = ()):
    teachers = f"algo.teachers=[{','.join(paths)}]"
    return compose_config([*TINY, *TENSOR, *CRASH_HEAD, "algo=distill", teachers, *extra])


def head_with_logits(crash: torch.Tensor) -> CrashHead:
    """A crash head that gives every state the crash logits ``crash`` (policy logits 0)."""
    n = crash.shape[-1]
    net = torch.nn.Linear(1, 2 * n)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(torch.cat([torch.zeros(n), crash]))
    return CrashHead(net, n)


def test_the_loss_is_the_cross_entropy_to_the_teachers_odds_worked_by_hand():
    # Student p = (1/2, 1/4); teachers q = (1/2, 3/4).
    loss = TeacherCrashLoss(head_with_logits(torch.tensor([0.0, -math.log(3.0)])), coeff=2.0)
    data = TensorDict(
        observation=torch.zeros(1, 1),
        teacher_crash_logits=torch.tensor([[0.0, math.log(3.0)]]),
        batch_size=[1],
    )
    out = loss(data)
    second = -(0.75 * math.log(0.25) + 0.25 * math.log(0.75))
    bce = (math.log(2.0) + second) / 2
    floor = (math.log(2.0) - (0.75 * math.log(0.75) + 0.25 * math.log(0.25))) / 2
    assert float(out["loss_teacher_crash"]) == pytest.approx(2.0 * bce, abs=1e-6)
    assert float(out["teacher_crash_excess"]) == pytest.approx(bce - floor, abs=1e-6)
    # The student's least likely crash is action 1, the teachers' action 0.
    assert float(out["teacher_crash_agreement"]) == 0.0
    # At the teachers' odds: nothing in excess, and no gradient.
    fitted = TeacherCrashLoss(head_with_logits(data["teacher_crash_logits"][0]), coeff=1.0)
    out = fitted(data)
    out["loss_teacher_crash"].backward()
    assert float(out["teacher_crash_excess"]) == pytest.approx(0.0, abs=1e-6)
    assert fitted.head.net.bias.grad.abs().max() < 1e-6


def test_the_loss_refuses_a_head_without_crash_logits_and_odds_of_other_actions():
    with pytest.raises(TypeError, match="the student needs model.crash_head=true"):
        TeacherCrashLoss(torch.nn.Linear(1, 2), coeff=1.0)
    with pytest.raises(ValueError, match="coeff must be a finite number > 0"):
        TeacherCrashLoss(head_with_logits(torch.zeros(2)), coeff=0.0)
    data = TensorDict(
        observation=torch.zeros(2, 1), teacher_crash_logits=torch.zeros(2, 5), batch_size=[2]
    )
    with pytest.raises(ValueError, match=r"the teachers have \(2, 5\) crash logits, the student"):
        TeacherCrashLoss(head_with_logits(torch.zeros(3)), coeff=1.0)(data)


def test_teachers_label_their_mean_crash_logits_and_a_headless_teacher_is_named(teachers):
    paths = [teachers["crash3"], teachers["crash1"]]
    cfg = student_config(paths)
    env = make_env(cfg.env)
    states = visited_states(16, seed=7)
    expected = []
    for path in paths:  # each checkpoint's own crash head
        ckpt = load_checkpoint(path)
        policy = make_policy(cfg.model, env)  # the same network as both teachers'
        policy.load_state_dict(ckpt["policy"])
        head = next(m for m in policy.modules() if isinstance(m, CrashHead))
        expected.append(head.crash_logits(states["observation"]).detach())
    assert not torch.allclose(expected[0], expected[1])
    labelled = load_teachers(paths, cfg.env, env, crash_key="crash")(states.clone())
    torch.testing.assert_close(labelled["crash"], (expected[0] + expected[1]) / 2)
    with pytest.raises(ValueError, match=r"teacher .*headless/last.pt has none"):
        load_teachers([teachers["crash3"], teachers["headless"]], cfg.env, env, crash_key="c")
    # A student without a crash head still learns from a headless teacher.
    load_teachers([teachers["headless"]], cfg.env, env)


def test_a_student_learns_its_teachers_crash_odds_and_grpo_continues_from_it(teachers, tmp_path):
    # A larger step: Adam moves each weight by about lr per step, and the odds are far.
    extra = ["experiment.total_frames=640", "rollout.frames_per_batch=64", "optim.lr=0.01"]
    cfg = student_config(
        [teachers["crash3"], teachers["crash1"]], [*extra, "algo.max_minibatches=40"]
    )
    trainer = Trainer(cfg, run_dir=tmp_path / "student")
    held_out = visited_states(32, seed=123)
    labelled = trainer.algo.teachers(held_out.clone())
    loss = TeacherCrashLoss(trainer.algo.crash_head.head, coeff=1.0)

    def excess() -> float:
        with torch.no_grad():
            return float(loss(labelled)["teacher_crash_excess"])

    before = excess()
    trainer.train()
    assert excess() < 0.1 * before  # measured: 0.18 to 0.0007
    # The student keeps a crash head: GRPO with the survival bootstrap starts from it.
    student = tmp_path / "student" / "last.pt"
    grpo = compose_config(
        [*TINY, *TENSOR, *CRASH_HEAD, "algo=grpo_lab", "algo.bootstrap=survival"]
        + [f"init_from={student}"]
    )
    continued = Trainer(grpo, run_dir=tmp_path / "grpo")
    saved = load_checkpoint(student)["policy"]
    for key, value in continued.policy.state_dict().items():
        assert torch.equal(saved[key], value), key


def test_start_from_run_starts_the_student_from_its_first_teachers_weights(teachers, tmp_path):
    # experiment=search_student_pair's student: the first teacher's network, at aversion 0.
    paths = [teachers["crash3"], teachers["crash1"]]
    student = Trainer(
        student_config(paths, ["algo.start_from_run=true", "model.crash_aversion=0"]),
        run_dir=tmp_path / "refit",
    )
    first = load_checkpoint(teachers["crash3"])["policy"]
    weights = student.policy.state_dict()
    assert first.keys() == weights.keys()
    for key, value in first.items():
        assert torch.equal(weights[key], value), key
    fresh = Trainer(student_config(paths), run_dir=tmp_path / "fresh")  # the control
    assert not torch.equal(fresh.policy.state_dict()[OUTPUT_BIAS], first[OUTPUT_BIAS])
    with pytest.raises(ValueError, match=r"start_from_run=true starts the student from its first"):
        check_config(student_config(paths, ["algo.start_from_run=true", f"init_from={paths[1]}"]))
