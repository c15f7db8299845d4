"""``algo.teacher_runs``: the teachers of a distillation trained first, from the same command.

``python scripts/train.py experiment=best`` runs the pipeline of the best single network
(docs/results.md, recipe 4): each entry of ``algo.teacher_runs`` is one teacher run's
overrides, trained into ``<run>/teachers/<i>/``; the student (``algo=distill``) then
learns from their checkpoints and ends with the final evaluation on highway-env.

A stage is done when its folder holds ``done.json``. Run the same command again after
an interruption: the finished teachers are skipped, an unfinished one resumes from its
``last.pt``, and so does the student. One progress bar spans every stage's frames.
"""

from __future__ import annotations

import json
import logging
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.compose import compose_config
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

    A teacher whose folder holds a checkpoint but no ``done.json`` resumes from it.

    Raises:
        ValueError: an entry does not compose (naming it), or asks for a distillation.

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
        if (folder / "last.pt").exists() and not (folder / DONE).exists():
            overrides.append(f"resume={folder / 'last.pt'}")
        try:
            teacher = compose_config(overrides, conf_dir=conf_dir)
        except Exception as err:  # Hydra's errors name the key; say which teacher
            raise ValueError(f"algo.teacher_runs[{index}] ({spec!r}): {err}") from err
        if str(teacher.algo.name) == "distill":
            raise ValueError(f"algo.teacher_runs[{index}] ({spec!r}) is a distillation itself")
        out.append((folder, teacher))
    return out


class _PipelineBar(Hook):
    """Moves the pipeline's bar by each iteration's frames."""

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


def _frames_done(folder: Path) -> int:
    # A finished stage says its frames in done.json: no checkpoint to read for the bar.
    if (folder / DONE).exists():
        return int(json.loads((folder / DONE).read_text())["frames"])
    path = folder / "last.pt"
    return int(load_checkpoint(path)["frames"]) if path.exists() else 0


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

    The student (``cfg``, an ``algo=distill`` config) learns from ``algo.teachers`` plus
    the teacher runs' checkpoints, in ``run_dir``; a student checkpoint there without
    ``done.json`` is resumed.

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
    run_dir = Path(run_dir)
    teachers = teacher_configs(cfg, run_dir, conf_dir)
    stages = [(folder, teacher) for folder, teacher in teachers if not (folder / DONE).exists()]
    total = sum(int(t.experiment.total_frames) for _, t in teachers)
    total += int(cfg.experiment.total_frames)
    done = sum(_frames_done(folder) for folder, _ in teachers) + _frames_done(run_dir)
    bar = tqdm(total=total, initial=done, unit="frame", disable=not sys.stderr.isatty())
    try:
        for folder, teacher in stages:
            log.info("teacher %s: %s", folder.name, folder)
            result = _train(teacher, folder, [*hooks, _PipelineBar(bar)])
            if result.interrupted:
                return result
        paths = [str(path) for path in cfg.algo.get("teachers") or []]
        paths += [str(folder / "last.pt") for folder, _ in teachers]
        student = OmegaConf.merge(cfg, {"algo": {"teachers": paths}})
        if (run_dir / "last.pt").exists() and not (run_dir / DONE).exists():
            student.resume = str(run_dir / "last.pt")
        return _train(student, run_dir, [*hooks, _PipelineBar(bar)])
    finally:
        bar.close()
