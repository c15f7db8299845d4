"""experiment=best's pipeline: teachers trained first, then the student; a rerun resumes."""

from __future__ import annotations

import os

import pytest
import torch
from train_setup import TINY, compose_config

from torchrl_grpo.training import load_checkpoint, teacher_runs
from torchrl_grpo.training.config import check_config
from torchrl_grpo.training.hooks import Hook
from torchrl_grpo.training.resolvers import CONF_DIR
from torchrl_grpo.training.teacher_runs import (
    DONE,
    _pipeline_frames,
    _stage_tree,
    teacher_configs,
    train_with_teachers,
)

TEACHER = " ".join(TINY)
STUDENT = [*TINY, "algo=distill", "experiment.total_frames=20", "algo.replay_frames=64"]


def _student(*teacher_frames: int, extra: tuple[str, ...] = ()) -> list[str]:
    runs = ",".join(
        f"'{TEACHER} seed={i} experiment.total_frames={n}'" for i, n in enumerate(teacher_frames)
    )
    return [*STUDENT, f"algo.teacher_runs=[{runs}]", *extra]


def test_the_teachers_train_first_and_the_student_learns_from_their_checkpoints(tmp_path):
    result = train_with_teachers(compose_config(_student(20, 20)), tmp_path)
    assert not result.interrupted and result.frames >= 20
    teachers = [tmp_path / "teachers" / str(i) for i in range(2)]
    for folder in teachers:
        assert (folder / DONE).exists() and load_checkpoint(folder / "last.pt")["frames"] >= 20
    student = load_checkpoint(tmp_path / "last.pt")
    assert student["config"]["algo"]["teachers"] == [str(f / "last.pt") for f in teachers]
    assert (tmp_path / DONE).exists()
    # Two seeds: two different teachers (the control that the runs are distinct).
    a, b = (load_checkpoint(f / "last.pt")["policy"] for f in teachers)
    assert any(not torch.equal(a[k], b[k]) for k in a)
    # The same command again trains nothing: the student resumes at its end.
    counted = _CountIterations()
    again = train_with_teachers(compose_config(_student(20, 20)), tmp_path, hooks=[counted])
    rerun = load_checkpoint(tmp_path / "last.pt")
    assert counted.iterations == 0 and again.frames == result.frames
    assert (rerun["frames"], rerun["iteration"]) == (student["frames"], student["iteration"])
    for key, value in student["policy"].items():
        assert torch.equal(rerun["policy"][key], value), key


@pytest.mark.slow  # 13 s: three stages trained twice
def test_a_rerun_skips_finished_teachers_and_resumes_the_unfinished_one(tmp_path):
    train_with_teachers(compose_config(_student(20, 20)), tmp_path)
    first = tmp_path / "teachers" / "0" / "last.pt"
    untouched = first.read_bytes()
    # Teacher 1 as if interrupted after its first batch of a 200-frame budget.
    (tmp_path / "teachers" / "1" / DONE).unlink()
    (tmp_path / DONE).unlink()
    stopped = load_checkpoint(tmp_path / "teachers" / "1" / "last.pt")
    train_with_teachers(compose_config(_student(20, 200)), tmp_path)
    assert first.read_bytes() == untouched  # a finished teacher is not trained again
    resumed = load_checkpoint(tmp_path / "teachers" / "1" / "last.pt")
    assert resumed["frames"] >= 200 and resumed["iteration"] > stopped["iteration"]
    assert (tmp_path / "teachers" / "1" / DONE).exists() and (tmp_path / DONE).exists()


class _CountIterations(Hook):
    def __init__(self):
        self.iterations = 0

    def due(self, trainer, batch):
        return True

    def on_iteration(self, trainer, batch, result):
        self.iterations += 1
        return {}


class _RecordProcess(Hook):
    def on_train_start(self, trainer, result):
        (trainer.run_dir / "pid").write_text(str(os.getpid()))


class _StopTeacher(Hook):
    def due(self, trainer, batch):
        return trainer.run_dir.name == "0"

    def on_iteration(self, trainer, batch, result):
        trainer.stop_requested = True  # as Ctrl-C does
        return {}


def test_an_interrupted_teacher_stops_the_pipeline_before_the_student(tmp_path):
    result = train_with_teachers(compose_config(_student(60, 20)), tmp_path, hooks=[_StopTeacher()])
    assert result.interrupted
    assert not (tmp_path / "teachers" / "0" / DONE).exists()
    assert not (tmp_path / "teachers" / "1").exists() and not (tmp_path / "last.pt").exists()


def test_a_distillation_among_the_teachers_runs_its_own_pipeline_first(tmp_path, monkeypatch):
    cfg = compose_config(_student())
    # The teacher is a distillation of a run of its own (experiment=search_student_round2's shape).
    cfg.algo.teacher_runs = [
        f"{' '.join(STUDENT)} \"algo.teacher_runs=['{TEACHER} experiment.total_frames=20']\""
    ]
    inner, innermost = tmp_path / "teachers" / "0", tmp_path / "teachers" / "0" / "teachers" / "0"
    assert _pipeline_frames(_stage_tree(cfg, tmp_path, CONF_DIR)) == (60, 0)  # one bar, 3 stages
    composed, compose = [], teacher_runs.compose_config
    monkeypatch.setattr(
        teacher_runs, "compose_config", lambda *a, **k: composed.append(a) or compose(*a, **k)
    )
    stopped = train_with_teachers(cfg, tmp_path, hooks=[_StopTeacher()])
    assert len(composed) == 2  # each teacher's config once, for the bar and the run alike
    assert (
        stopped.interrupted and stopped.run_dir == innermost and not inner.joinpath(DONE).exists()
    )
    result = train_with_teachers(cfg, tmp_path)
    assert not result.interrupted
    assert all((folder / DONE).exists() for folder in (innermost, inner, tmp_path))
    assert load_checkpoint(inner / "last.pt")["config"]["algo"]["teachers"] == [
        str(innermost / "last.pt")
    ]
    assert load_checkpoint(tmp_path / "last.pt")["config"]["algo"]["teachers"] == [
        str(inner / "last.pt")
    ]
    counted = _CountIterations()
    train_with_teachers(cfg, tmp_path, hooks=[counted])
    assert counted.iterations == 0  # every stage done: nothing trains again


def test_teacher_runs_nested_too_deep_are_refused_before_any_training(tmp_path, monkeypatch):
    # An entry naming its own experiment nests without end; a depth limit names it.
    monkeypatch.setattr(teacher_runs, "MAX_NESTING", 0)
    cfg = compose_config(_student())
    cfg.algo.teacher_runs = [f"{' '.join(STUDENT)} \"algo.teacher_runs=['{TEACHER}']\""]
    with pytest.raises(ValueError, match="algo.teacher_runs nest more than 0 deep"):
        train_with_teachers(cfg, tmp_path)
    assert not (tmp_path / "teachers").exists()


def test_experiment_search_student_round2_nests_the_first_round_and_starts_from_it(tmp_path):
    cfg = compose_config(["experiment=search_student_round2"])
    check_config(cfg)
    ((folder, first),) = teacher_configs(cfg, tmp_path)
    ((_, run),) = teacher_configs(first, folder)
    assert (str(cfg.algo.name), str(first.algo.name), str(run.algo.name)) == (
        "search_distill",
        "search_distill",
        "grpo_branch",
    )
    assert cfg.algo.start_from_run and not first.algo.start_from_run
    assert cfg.model.crash_aversion == 800 and first.model.crash_aversion == 200


def test_experiment_search_student_pair_distils_two_seeds_of_the_second_round(tmp_path):
    cfg = compose_config(["experiment=search_student_pair"])
    check_config(cfg)
    pair = teacher_configs(cfg, tmp_path)
    firsts = [teacher_configs(run, folder)[0][1] for folder, run in pair]
    assert [(run.seed, str(run.algo.name)) for _, run in pair] == [
        (0, "search_distill"),
        (1, "search_distill"),
    ]
    assert [first.seed for first in firsts] == [0, 1]  # each round of the second seeded 1
    assert all(run.model.crash_aversion == 800 and run.algo.start_from_run for _, run in pair)
    assert str(cfg.algo.name) == "distill" and cfg.algo.start_from_run
    assert cfg.model.crash_aversion == 0 and cfg.algo.teacher_processes == 2
    assert cfg.env.config == pair[0][1].env.config  # the student observes what they do


def test_experiment_best_composes_nine_teachers_of_the_documented_recipe(tmp_path):
    cfg = compose_config(["experiment=best"])
    check_config(cfg)  # teacher_runs stand for algo.teachers
    runs = teacher_configs(cfg, tmp_path)
    assert len(runs) == 9 and str(cfg.algo.name) == "distill" and cfg.algo.teacher_processes == 2
    assert [int(t.experiment.total_frames) for _, t in runs] == [4_000_000] * 6 + [2_000_000] * 3
    assert {str(t.algo.bootstrap) for _, t in runs} == {"survival"}
    assert [t.model.get("ensemble", 1) for _, t in runs] == [1] * 6 + [3, 3, 1]
    with pytest.raises(ValueError, match=r"algo.teacher_runs\[0\]"):
        teacher_configs(compose_config([*STUDENT, "algo.teacher_runs=['algo.nope=1']"]), tmp_path)


@pytest.mark.slow  # two whole pipelines; the next test runs the teachers' processes too
def test_teachers_in_two_processes_train_the_same_weights_as_one_after_another(tmp_path):
    # Each forked teacher runs with cores // 2 torch threads; the sequential control runs
    # with as many, so the two differ only in where the teachers train.
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, len(os.sched_getaffinity(0)) // 2))
    try:
        train_with_teachers(compose_config(_student(20, 40)), tmp_path / "serial")
    finally:
        torch.set_num_threads(threads)
    cfg = compose_config(_student(20, 40, extra=("algo.teacher_processes=2",)))
    result = train_with_teachers(cfg, tmp_path / "forked")
    assert not result.interrupted and (tmp_path / "forked" / DONE).exists()
    for i in range(2):
        serial = load_checkpoint(tmp_path / "serial" / "teachers" / str(i) / "last.pt")
        forked = load_checkpoint(tmp_path / "forked" / "teachers" / str(i) / "last.pt")
        assert forked["frames"] == serial["frames"] >= 20
        assert serial["policy"].keys() == forked["policy"].keys()
        for key, weights in serial["policy"].items():
            assert torch.equal(forked["policy"][key], weights), key


def test_an_interrupted_teacher_process_stops_the_pipeline_before_the_student(tmp_path):
    cfg = compose_config(_student(60, 20, 20, extra=("algo.teacher_processes=2",)))
    result = train_with_teachers(cfg, tmp_path, hooks=[_StopTeacher()])
    assert result.interrupted and result.run_dir == tmp_path / "teachers" / "0"
    assert (tmp_path / "teachers" / "0" / "last.pt").exists()
    assert not (tmp_path / "teachers" / "0" / DONE).exists()
    assert not (tmp_path / "last.pt").exists()  # no student


class _StopAt(Hook):
    def __init__(self, folder):
        self.folder = folder

    def due(self, trainer, batch):
        return trainer.run_dir == self.folder

    def on_iteration(self, trainer, batch, result):
        trainer.stop_requested = True  # as Ctrl-C does
        return {}


def test_a_nested_student_stopped_midway_resumes_with_its_teachers_named(tmp_path, caplog):
    cfg = compose_config(_student())
    cfg.algo.teacher_runs = [
        f"{' '.join(STUDENT)} experiment.total_frames=200 "
        f"\"algo.teacher_runs=['{TEACHER} experiment.total_frames=20']\""
    ]
    inner = tmp_path / "teachers" / "0"
    assert train_with_teachers(cfg, tmp_path, hooks=[_StopAt(inner)]).interrupted
    stopped = load_checkpoint(inner / "last.pt")
    assert stopped["frames"] < 200 and not (inner / DONE).exists()
    with caplog.at_level("WARNING"):
        result = train_with_teachers(cfg, tmp_path)
    assert not result.interrupted and (inner / DONE).exists()
    resumed = load_checkpoint(inner / "last.pt")
    assert resumed["iteration"] > stopped["iteration"] and resumed["frames"] >= 200
    assert resumed["config"]["algo"]["teachers"] == [str(inner / "teachers" / "0" / "last.pt")]
    # Its pipeline fills in its teachers: no warning that the resume drops them.
    assert "the checkpoint's run had" not in caplog.text


def test_distillations_among_the_teachers_run_their_pipelines_in_their_processes(tmp_path):
    # experiment=search_student_pair's shape: each teacher a pipeline of its own, two at once.
    cfg = compose_config(_student(extra=("algo.teacher_processes=2",)))
    cfg.algo.teacher_runs = [
        f"{' '.join(STUDENT)} seed={i} \"algo.teacher_runs=['{TEACHER} seed={i} "
        "experiment.total_frames=20']\""
        for i in range(2)
    ]
    inner = [tmp_path / "teachers" / str(i) for i in range(2)]
    innermost = [folder / "teachers" / "0" for folder in inner]
    stopped = train_with_teachers(cfg, tmp_path, hooks=[_StopTeacher()])
    # Both innermost runs are named "0": each process stops its own, before its student.
    assert stopped.interrupted and stopped.run_dir in innermost
    assert not any((folder / "last.pt").exists() for folder in inner)
    assert not (tmp_path / "last.pt").exists()
    result = train_with_teachers(cfg, tmp_path, hooks=[_RecordProcess()])
    assert not result.interrupted
    assert all((folder / DONE).exists() for folder in (*innermost, *inner, tmp_path))
    # Each teacher's pipeline, its own run and its student, trained in one forked process.
    pids = [
        {int((f / "pid").read_text()) for f in pair} for pair in zip(inner, innermost, strict=True)
    ]
    assert all(len(pid) == 1 for pid in pids) and len(set.union(*pids)) == 2
    assert os.getpid() not in set.union(*pids)
    for folder, run in zip(inner, innermost, strict=True):
        assert load_checkpoint(folder / "last.pt")["config"]["algo"]["teachers"] == [
            str(run / "last.pt")
        ]
    assert load_checkpoint(tmp_path / "last.pt")["config"]["algo"]["teachers"] == [
        str(folder / "last.pt") for folder in inner
    ]


def test_fewer_than_one_teacher_process_is_refused():
    with pytest.raises(ValueError, match="algo.teacher_processes must be at least 1"):
        check_config(compose_config(_student(20, extra=("algo.teacher_processes=0",))))
