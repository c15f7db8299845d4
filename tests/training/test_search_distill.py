"""Search distillation (``algo=search_distill``): the labels, the config, a run, resume."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from train_setup import TINY, compose_config

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import VehicleTransformer, make_scripted_policy
from torchrl_grpo.objectives import SearchLabelLoss
from torchrl_grpo.training import Trainer, load_checkpoint
from torchrl_grpo.training.algos.search_distill import search_labels
from torchrl_grpo.training.config import check_config
from torchrl_grpo.training.teacher_runs import DONE, train_with_teachers

TENSOR = ["env.backend=tensor", "env.num_envs=16"]
STUDENT = ["algo=search_distill", "model=transformer", "algo.horizon=3"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny GRPO run on the tensor simulator: the run the search is over."""
    root = tmp_path_factory.mktemp("searched")
    cfg = compose_config([*TINY, *TENSOR, "experiment.total_frames=60"])
    Trainer(cfg, run_dir=root).train()
    return str(root / "last.pt")


def student_config(run: str, extra: list[str] = ()):
    return compose_config([*TINY, *TENSOR, *STUDENT, f"algo.teachers=[{run}]", *extra])


def test_labels_are_each_branch_replayed_alone_from_the_state():
    env = TensorHighwayEnv("highway-fast-v0", num_envs=3, return_state=True, seed=4)
    td = env.reset()
    for _ in range(3):  # states a few steps in, with traffic around
        td = env.step(td.set("action", torch.full((3,), 3)))["next"]
    slower = make_scripted_policy("slower")
    planner = LookaheadPolicy(TensorHighwayEnv("highway-fast-v0", num_envs=15), slower, 4)
    labels = search_labels(planner, td)
    assert torch.equal(labels["observation"], td["observation"])
    # The reference: one world restored from the row's state, the action, then SLOWER.
    one = TensorHighwayEnv("highway-fast-v0", num_envs=1, seed=0)
    for row in range(3):
        for action in range(5):
            state = td["state"][row : row + 1].clone()
            step = one.reset(TensorDict(state=state, batch_size=[1]), set_state=True)
            total, crashed = 0.0, False
            for t in range(4):
                step.set("action", torch.tensor([action if t == 0 else 4]))
                out = one.step(step)["next"]
                total += float(out["reward"].sum())
                if bool(out["done"].any()):
                    crashed = bool(out["crashed"].any())
                    break
                step = out
            assert labels["search_scores"][row, action] == pytest.approx(total, abs=1e-5)
            assert bool(labels["search_crashed"][row, action]) == crashed


def test_the_config_needs_one_run_a_crash_head_and_the_tensor_simulator(run):
    with pytest.raises(ValueError, match=r"searches over one run: .*\(got 0 runs\)"):
        check_config(compose_config([*TINY, *STUDENT]))
    with pytest.raises(ValueError, match=r"\(got 2 runs\)"):
        check_config(compose_config([*TINY, *STUDENT, f"algo.teachers=[{run},{run}]"]))
    with pytest.raises(ValueError, match="needs model.crash_head=true"):
        check_config(student_config(run, ["model.crash_head=false"]))
    with pytest.raises(ValueError, match="does not cover env.scenario=racetrack-v0"):
        check_config(student_config(run, ["env.scenario=racetrack-v0"]))
    with pytest.raises(ValueError, match=r"algo.horizon must be >= 1"):
        check_config(student_config(run, ["algo.horizon=0"]))
    check_config(student_config(run))


def test_the_student_fits_the_search_on_its_own_states(run, tmp_path):
    cfg = student_config(
        run,
        [
            "experiment.total_frames=640",
            "rollout.frames_per_batch=64",
            "algo.max_minibatches=30",
            "algo.minibatch_size=64",
            "optim.lr=3e-3",
            "experiment.eval_every=5",
        ],
    )
    trainer = Trainer(cfg, run_dir=tmp_path / "student")
    net = next(m for m in trainer.policy.modules() if isinstance(m, VehicleTransformer))
    assert not net.standardised
    untrained = copy.deepcopy(trainer.algo.loss.head)
    result = trainer.train()
    assert (result.iterations, trainer.frames) == (10, 640)
    assert len(trainer.algo.replay) == 640 and bool(net.standardised)
    # Every state's 5 branches of at most 3 steps are counted apart from the frames.
    assert 640 * 5 <= trainer.algo.search_frames <= 640 * 5 * 3
    # Each evaluation's row records the branch steps so far: none before the first batch.
    searched = [row["search_frames"] for row in trainer.progress.eval_history]
    assert len(searched) == 3 and searched[0] == 0 < searched[1] < searched[2]
    assert searched[2] == trainer.algo.search_frames
    kept = trainer.algo.replay.rows  # the states it drove itself, labelled by the search

    def fit(head) -> dict[str, float]:
        loss = SearchLabelLoss(head, regret_coeff=3.0, crash_coeff=1.0)
        with torch.no_grad():
            return {k: float(v) for k, v in loss(kept).items()}

    before, after = fit(untrained), fit(trainer.algo.loss.head)
    for term in ("loss_best_set", "loss_search_regret", "loss_search_crash"):
        assert after[term] < 0.8 * before[term], term


def test_the_student_drives_greedily_as_it_is_evaluated(run, tmp_path):
    # Without crash aversion an untrained student's logits are nearly flat, so a
    # sampling collector would almost surely play some other action in 64 steps.
    cfg = student_config(run, ["rollout.frames_per_batch=64", "model.crash_aversion=0"])
    trainer = Trainer(cfg, tmp_path / "s")
    collector = trainer.algo.make_collector(seed=3)
    try:
        batch = next(iter(collector)).reshape(-1)
    finally:
        collector.shutdown()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        greedy = trainer.policy(batch.select("observation").clone())["action"]
    assert torch.equal(batch["action"], greedy)


def test_resume_of_a_search_distillation_continues_exactly(run, tmp_path):
    common = [
        "experiment.checkpoint_every=1",
        "algo.replay_frames=100",
        "algo.max_minibatches=2",
        "algo.minibatch_size=32",
        "rollout.frames_per_batch=32",
    ]

    def train(name, frames):
        trainer = Trainer(
            student_config(run, [*common, f"experiment.total_frames={frames}"]),
            run_dir=tmp_path / name,
        )
        trainer.train()
        return trainer

    straight = train("straight", 160)
    stopped = train("stopped", 64)
    cfg = compose_config(
        [f"resume={tmp_path / 'stopped' / 'last.pt'}", "experiment.total_frames=160"]
    )
    resumed = Trainer(cfg, run_dir=tmp_path / "resumed")
    resumed.train()
    assert resumed.algo.search_frames == straight.algo.search_frames
    a, b, c = (t.policy.state_dict() for t in (straight, resumed, stopped))
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert any(not torch.equal(a[k], c[k]) for k in a)  # the control: it can fail


@pytest.mark.slow  # train_with_teachers runs fast in test_teacher_runs.py (with algo=distill)
def test_one_command_trains_the_searched_run_then_the_student(tmp_path):
    teacher = "experiment=smoke env.backend=tensor env.num_envs=16 experiment.total_frames=40"
    cfg = compose_config(
        [
            *TINY,
            *TENSOR,
            *STUDENT,
            f"algo.teacher_runs=['{teacher}']",
            "experiment.total_frames=64",
            "rollout.frames_per_batch=32",
            "algo.minibatch_size=32",
        ]
    )
    check_config(cfg)
    result = train_with_teachers(cfg, tmp_path)
    assert (tmp_path / "teachers" / "0" / DONE).exists() and (tmp_path / DONE).exists()
    saved = load_checkpoint(result.checkpoint)["config"]["algo"]
    assert saved["teachers"] == [str(tmp_path / "teachers" / "0" / "last.pt")]
    assert saved["teacher_runs"] == []


def test_start_from_run_starts_the_student_from_the_weights_it_searches_over(run, tmp_path):
    tiny = ["rollout.frames_per_batch=32", "algo.max_minibatches=2", "algo.minibatch_size=32"]
    first = student_config(run, [*tiny, "experiment.total_frames=32"])
    Trainer(first, run_dir=tmp_path / "first").train()
    searched = str(tmp_path / "first" / "last.pt")  # a search student: the next round's run
    saved = load_checkpoint(searched)["policy"]
    second = Trainer(
        student_config(searched, ["algo.start_from_run=true", "model.crash_aversion=800"]),
        run_dir=tmp_path / "second",
    )
    weights = second.policy.state_dict()
    for key, value in saved.items():
        assert torch.equal(weights[key], value), key
    fresh = Trainer(student_config(searched), run_dir=tmp_path / "fresh")  # the control
    assert any(not torch.equal(fresh.policy.state_dict()[k], v) for k, v in saved.items())
    with pytest.raises(
        ValueError, match=r"start_from_run=true starts the student .* drop init_from="
    ):
        check_config(student_config(searched, ["algo.start_from_run=true", f"init_from={run}"]))
