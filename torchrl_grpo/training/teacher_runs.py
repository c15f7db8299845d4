"""``algo.teacher_runs``: the teachers of a distillation trained first, from the same command.

``python scripts/train.py experiment=best`` runs the pipeline of the best single network
(docs/results.md, recipe 4): each entry of ``algo.teacher_runs`` is one teacher run's
overrides, trained into ``<run>/teachers/<i>/``; the student (``algo=distill``) then
learns from their checkpoints and ends with the final evaluation on highway-env.

A stage is done when its folder holds ``done.json``. Run the same command again after
an interruption: the finished teachers are skipped, an unfinished one resumes from its
``last.pt``, and so does the student, finished or not (a finished one is evaluated
again, and continued if the command asks for more frames). One progress bar spans
every stage's frames.

With ``algo.teacher_processes = n > 1`` the teachers train ``n`` at a time, each in a
forked process with ``cores // n`` torch threads: a run scales poorly past one thread
here, so two one-thread teachers on 2 cores train about twice the frames a second of one
two-thread teacher. A teacher that is a pipeline of its own trains all its stages in its
process (``experiment=search_student_pair``: two second rounds side by side).

A teacher run may be a distillation itself (its entry has ``algo.teacher_runs`` of its
own): its pipeline runs first, in its folder, under the same bar. That is how
``experiment=search_student_round2`` chains expert iteration's rounds: the search over
the first round's student labels the second's.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import shlex
import sys
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.compose import compose_config, resume_config
from torchrl_grpo.training.hooks import Hook
from torchrl_grpo.training.resolvers import CONF_DIR
from torchrl_grpo.training.trainer import Trainer, TrainResult

__all__ = ["DONE", "train_with_teachers", "teacher_configs"]

log = logging.getLogger(__name__)

#: The file a finished stage writes into its folder.
DONE = "done.json"


def teacher_configs(
    cfg: DictConfig, run_dir: str | Path, conf_dir: str | Path = CONF_DIR
) -> list[tuple[Path, DictConfig]]:
    """Each teacher run's folder and config, composed from its entry of ``algo.teacher_runs``.

    A teacher whose folder holds a checkpoint but no ``done.json`` resumes from it (a
    teacher that is a pipeline of its own is resumed by its pipeline instead, once its
    teachers' checkpoints are known).

    Raises:
        ValueError: an entry does not compose (naming it).

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training import compose_config
        >>> cfg = compose_config(["algo=distill",
        ...     "algo.teacher_runs=['experiment=smoke seed=1','experiment=smoke seed=2']"])
        >>> [(path.name, run.seed) for path, run in teacher_configs(cfg, tempfile.mkdtemp())]
        [('0', 1), ('1', 2)]
    """
    out = []
    for index, spec in enumerate(cfg.algo.get("teacher_runs") or []):
        folder = Path(run_dir) / "teachers" / str(index)
        overrides = [*shlex.split(str(spec)), f"experiment.out_dir={folder}"]
        try:
            teacher = compose_config(overrides, conf_dir=conf_dir)
            resumable = (folder / "last.pt").exists() and not (folder / DONE).exists()
            if resumable and not teacher.algo.get("teacher_runs"):
                # The checkpoint's config with the entry's overrides on top, as resume= gives.
                teacher.resume = str(folder / "last.pt")
                teacher = resume_config(teacher, overrides, conf_dir=conf_dir)
        except Exception as err:  # Hydra's errors name the key; say which teacher
            raise ValueError(f"algo.teacher_runs[{index}] ({spec!r}): {err}") from err
        out.append((folder, teacher))
    return out


class _PipelineBar(Hook):
    """Adds each iteration's new frames to the pipeline's bar (``bar.update``)."""

    phase = "pipeline"

    def __init__(self, bar: Any) -> None:
        self.bar = bar
        self.seen = 0

    def on_train_start(self, trainer: Any, result: Any) -> None:  # noqa: D102
        self.seen = trainer.progress.frames

    def due(self, trainer: Any, batch: Any) -> bool:  # noqa: D102
        return True

    def on_iteration(self, trainer: Any, batch: Any, result: Any) -> dict[str, Any]:  # noqa: D102
        frames = trainer.progress.frames
        self.bar.update(frames - self.seen)
        self.seen = frames
        return {}


class _SharedCount:
    """A ``bar.update`` stand-in in a teacher's process: adds to its slot of a shared array."""

    def __init__(self, counts: Any, slot: int) -> None:
        self.counts, self.slot = counts, slot

    def update(self, frames: int) -> None:
        self.counts[self.slot] += frames


def _frames_done(folder: Path) -> int:
    # A finished stage says its frames in done.json: no checkpoint to read for the bar.
    if (folder / DONE).exists():
        return int(json.loads((folder / DONE).read_text())["frames"])
    path = folder / "last.pt"
    return int(load_checkpoint(path)["frames"]) if path.exists() else 0


#: How deep teacher runs may nest: deeper, an entry most likely names its own experiment.
MAX_NESTING = 8


@dataclass(frozen=True)
class _Stage:
    """A pipeline's stage: its folder, its config and its teacher runs' stages."""

    folder: Path
    cfg: DictConfig
    teachers: tuple[_Stage, ...]


def _stage_tree(cfg: DictConfig, run_dir: Path, conf_dir: str | Path, depth: int = 0) -> _Stage:
    """Every stage of the pipeline, each config composed once for the bar and the run."""
    if depth > MAX_NESTING:
        raise ValueError(
            f"algo.teacher_runs nest more than {MAX_NESTING} deep (at {run_dir}): does an "
            "entry name the experiment it is in?"
        )
    teachers = tuple(
        _stage_tree(teacher, folder, conf_dir, depth + 1)
        for folder, teacher in teacher_configs(cfg, run_dir, conf_dir)
    )
    return _Stage(run_dir, cfg, teachers)


def _pipeline_frames(stage: _Stage) -> tuple[int, int]:
    """The frames a pipeline asks for and those already trained, its teachers' included."""
    total, done = int(stage.cfg.experiment.total_frames), _frames_done(stage.folder)
    for teacher in stage.teachers:
        teacher_total, teacher_done = _pipeline_frames(teacher)
        total, done = total + teacher_total, done + teacher_done
    return total, done


def _train(cfg: DictConfig, folder: Path, hooks: Sequence[Hook]) -> TrainResult:
    trainer = Trainer(cfg, run_dir=folder, hooks=hooks)
    trainer.show_progress = False  # the pipeline's bar spans every stage
    result = trainer.train()
    if not result.interrupted:
        (folder / DONE).write_text(json.dumps({"frames": result.frames}))
    return result


def train_with_teachers(
    cfg: DictConfig,
    run_dir: str | Path,
    conf_dir: str | Path = CONF_DIR,
    hooks: Sequence[Hook] = (),
) -> TrainResult:
    """Train the teachers of ``algo.teacher_runs`` that are not done, then the student.

    The student (``cfg``, an ``algo=distill`` or ``algo=search_distill`` config) learns
    from ``algo.teachers`` plus the teacher runs' checkpoints, in ``run_dir``; a student
    checkpoint there without ``done.json`` is resumed.

    Args:
        cfg: the student's config.
        run_dir: the pipeline's folder (the student's run folder).
        conf_dir: the config folder the teacher runs are composed in.
        hooks: extra hooks of every stage's trainer.

    Returns:
        The student's result, or the interrupted teacher's (``interrupted``).

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training import compose_config
        >>> tiny = "experiment=smoke logger=none experiment.final_eval_episodes=0"
        >>> cfg = compose_config(["algo=distill", "experiment=smoke", "logger=none",
        ...     f"algo.teacher_runs=['{tiny} experiment.total_frames=20']",
        ...     "experiment.total_frames=20", "experiment.final_eval_episodes=0",
        ...     "algo.replay_frames=64"])
        >>> result = train_with_teachers(cfg, tempfile.mkdtemp())
        >>> (result.run_dir / "teachers" / "0" / DONE).exists(), result.frames >= 20
        (True, True)
    """
    pipeline = _stage_tree(cfg, Path(run_dir), conf_dir)
    total, done = _pipeline_frames(pipeline)
    bar = tqdm(total=total, initial=done, unit="frame", disable=not sys.stderr.isatty())
    try:
        return _run_pipeline(pipeline, hooks, bar)
    finally:
        bar.close()


def _run_pipeline(
    pipeline: _Stage, hooks: Sequence[Hook], bar: Any, in_processes: bool = True
) -> TrainResult:
    """:func:`train_with_teachers` under a bar it was given (a nested pipeline's too).

    ``in_processes=False`` trains every teacher here, one after another: a pipeline
    inside a teacher's process, which has its share of the cores already.
    """
    pending = [teacher for teacher in pipeline.teachers if not (teacher.folder / DONE).exists()]
    processes = int(pipeline.cfg.algo.get("teacher_processes") or 1) if in_processes else 1
    processes = min(processes, len(pending))
    if processes > 1:
        stopped = _train_in_processes(pending, hooks, bar, processes)
        if stopped is not None:
            return stopped
    else:
        for teacher in pending:
            log.info("teacher %s: %s", teacher.folder.name, teacher.folder)
            result = _train_stage(teacher, hooks, bar, in_processes)
            if result.interrupted:
                return result
    paths = [str(path) for path in pipeline.cfg.algo.get("teachers") or []]
    paths += [str(teacher.folder / "last.pt") for teacher in pipeline.teachers]
    # The student's config names its teachers' checkpoints: the runs are done.
    student = OmegaConf.merge(pipeline.cfg, {"algo": {"teachers": paths, "teacher_runs": []}})
    run_dir = pipeline.folder
    if (run_dir / "last.pt").exists():
        # Finished or not: a finished student is not trained again, only evaluated
        # (or continued, when the command asks for more frames).
        student.resume = str(run_dir / "last.pt")
    return _train(student, run_dir, [*hooks, _PipelineBar(bar)])


def _train_stage(
    stage: _Stage, hooks: Sequence[Hook], bar: Any, in_processes: bool = True
) -> TrainResult:
    """One teacher: a run, or a distillation's whole pipeline (its own teachers first)."""
    if stage.teachers:
        return _run_pipeline(stage, hooks, bar, in_processes)
    return _train(stage.cfg, stage.folder, [*hooks, _PipelineBar(bar)])


_COUNTS: Any = None  # the pipeline's shared frame counts, inherited by a forked teacher


def _teacher_process(
    stage: _Stage, hooks: Sequence[Hook], slot: int, threads: int
) -> tuple[bool, Path, int, int]:
    torch.set_num_threads(threads)
    result = _train_stage(stage, hooks, _SharedCount(_COUNTS, slot), in_processes=False)
    return result.interrupted, result.run_dir, result.frames, result.iterations


def _train_in_processes(
    stages: Sequence[_Stage], hooks: Sequence[Hook], bar: Any, processes: int
) -> TrainResult | None:
    """Train ``stages`` ``processes`` at a time; an interrupted teacher's result, or None.

    A stage that is a pipeline of its own trains its teachers in its process too.
    """
    global _COUNTS
    if "fork" not in mp.get_all_start_methods():
        # A forked teacher inherits what this process registered (experimental algorithms,
        # network kinds); a spawned one would not know them.
        raise ValueError("algo.teacher_processes > 1 needs the fork start method (Linux)")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    threads = max(1, (cores or 1) // processes)
    context = mp.get_context("fork")
    _COUNTS = context.Array("q", len(stages), lock=False)
    start, stopped = bar.n, None
    pool = ProcessPoolExecutor(max_workers=processes, mp_context=context)
    try:
        pending: dict[Future, Path] = {}
        for slot, stage in enumerate(stages):
            folder = stage.folder
            log.info(
                "teacher %s: %s (%d at a time, %d threads each)",
                folder.name,
                folder,
                processes,
                threads,
            )
            job = pool.submit(_teacher_process, stage, hooks, slot, threads)
            pending[job] = folder
        while pending:
            try:
                finished, _ = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
            except KeyboardInterrupt:
                # Ctrl-C reached the running teachers too: they checkpoint and return.
                stopped = stopped or TrainResult(next(iter(pending.values())), interrupted=True)
                finished = set()
            bar.update(start + sum(_COUNTS) - bar.n)
            for job in finished:
                pending.pop(job)
                interrupted, folder, frames, iterations = job.result()
                if interrupted and stopped is None:
                    stopped = TrainResult(
                        folder,
                        folder / "last.pt",
                        frames=frames,
                        iterations=iterations,
                        interrupted=True,
                    )
            if stopped is not None:  # the queued teachers do not start
                pending = {job: folder for job, folder in pending.items() if not job.cancel()}
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        _COUNTS = None
    return stopped
