"""Metrics reach the logger as one row per training iteration."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from torchrl_grpo.training.logging_builder import log_metrics, make_logger


@pytest.fixture(autouse=True)
def _wandb_service_ends_with_the_test(monkeypatch):
    """Shut down the wandb service a test starts, so no later subprocess joins it."""
    yield
    wandb = pytest.importorskip("wandb")
    wandb.teardown()
    monkeypatch.delenv("WANDB_SERVICE", raising=False)


def test_wandb_gets_one_history_row_per_call(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = OmegaConf.create({"backend": "wandb", "mode": "offline", "project": "test"})
    logger = make_logger(cfg, tmp_path, "rows", {"seed": 0})
    rows = []
    real_log = logger.experiment.log

    def record(payload, *args, **kwargs):
        rows.append(dict(payload))
        return real_log(payload, *args, **kwargs)

    monkeypatch.setattr(logger.experiment, "log", record)
    try:
        log_metrics(logger, {"train/a": 1.0, "train/b": 2.0, "train/loss_c": 3.0}, step=10)
        log_metrics(logger, {"train/a": 4.0, "train/b": 5.0, "train/loss_c": 6.0}, step=20)
    finally:
        logger.experiment.finish()
    assert len(rows) == 2
    for row, expected in zip(rows, ((1.0, 2.0, 3.0), (4.0, 5.0, 6.0)), strict=True):
        assert tuple(row[k] for k in ("train/a", "train/b", "train/loss_c")) == expected


def test_csv_logger_writes_every_metric_at_its_step(tmp_path):
    logger = make_logger(OmegaConf.create({"backend": "csv"}), tmp_path, "csv", {"seed": 0})
    log_metrics(logger, {"train/a": 1.5, "train/none": None}, step=7)
    files = list((tmp_path / "csv").rglob("a.csv"))
    assert len(files) == 1 and files[0].read_text().strip() == "7,1.5"
    assert not list((tmp_path / "csv").rglob("none.csv"))


@pytest.mark.slow  # 11 s: a wandb run read back
def test_each_iteration_is_one_wandb_row_keyed_by_frames(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from train_setup import TINY, compose_config

    from torchrl_grpo.training import Trainer

    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = compose_config(
        [
            *TINY,
            "logger=wandb",
            "experiment.eval_every=1",
            "experiment.final_eval_episodes=1",
            "experiment.total_frames=100",
        ]
    )
    trainer = Trainer(cfg, run_dir=tmp_path / "run")
    rows = []
    real_log = trainer.logger.experiment.log

    def record(payload, *args, **kwargs):
        rows.append(dict(payload))
        return real_log(payload, *args, **kwargs)

    monkeypatch.setattr(trainer.logger.experiment, "log", record)
    result = trainer.train()
    # The evaluation before the first batch (frame 0), one row per iteration, then the
    # final evaluation's.
    assert result.iterations >= 2 and len(rows) == result.iterations + 2, [sorted(r) for r in rows]
    history = [json.loads(line) for line in (tmp_path / "run" / "eval_history.jsonl").open()]
    # Each row names its seed set: the periodic one, then the final one.
    exp = cfg.experiment
    assert [h["seed"] for h in history] == [exp.eval_seed] * (result.iterations + 1) + [
        exp.final_eval_seed
    ]
    zero, rows = rows[0], rows[1:]
    assert history[0]["frames"] == 0 and zero["eval/return"] == history[0]["return"]
    assert zero["eval/step"] == 0 and {name.split("/")[0] for name in zero} == {"eval"}
    history = history[1:]
    for row, evaluation in zip(rows[:-1], history, strict=False):
        frames = row["collect/frames"]
        # Every namespace's step is the frames; a row holds each of them.
        for ns in ("collect", "train", "eval", "time"):
            assert row[f"{ns}/step"] == frames, (ns, row)
        assert row["eval/return"] == evaluation["return"] and evaluation["frames"] == frames
        assert "train/loss_objective" in row and "time/collect" in row
        assert type(row["collect/branch_group"]).__name__ == "Video"
        assert {name.split("/")[0] for name in row} == {"collect", "train", "eval", "time"}
    frames = [r["collect/frames"] for r in rows[:-1]]
    assert frames == sorted(set(frames)), frames  # one row per iteration: growing frames
    final = rows[-1]
    assert final["eval/final_return"] == history[-1]["return"]
    assert type(final["eval/final_episode"]).__name__ == "Video"


def test_the_episode_video_reaches_the_offline_wandb_run_without_moviepy(tmp_path, monkeypatch):
    import hashlib
    import sys

    import torch
    from PIL import Image

    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_SILENT", "true")
    # The default install has no moviepy: an import of it fails here.
    for name in ("moviepy", "moviepy.editor", "moviepy.video.io.ImageSequenceClip"):
        monkeypatch.setitem(sys.modules, name, None)
    cfg = OmegaConf.create({"backend": "wandb", "mode": "offline", "project": "test"})
    logger = make_logger(cfg, tmp_path, "video", {"seed": 0})
    video = torch.zeros(1, 4, 3, 16, 24, dtype=torch.uint8)
    video[0, :, 0] = 200  # red frames, each with a yellowish band on top of its own height
    for t in range(4):
        video[0, t, 1, : 2 * (t + 1)] = 150
    try:
        log_metrics(logger, {"eval/final_return": 1.0, "eval/final_episode": video}, step=5)
    finally:
        logger.experiment.finish()
    import wandb

    wandb.teardown()  # the service writes the run's log asynchronously: flushed once it ends
    (run,) = (tmp_path / "wandb").glob("offline-run-*")
    (gif,) = (run / "files" / "media" / "videos").rglob("*.gif")
    with Image.open(gif) as image:
        frames = []
        for i in range(image.n_frames):
            image.seek(i)
            frames.append(np.asarray(image.convert("RGB")))
    assert len(frames) == 4 and frames[0].shape == (16, 24, 3)
    for t, frame in enumerate(frames):
        band = (frame == (200, 150, 0)).all(-1).all(-1)
        assert band.sum() == 2 * (t + 1) and tuple(frame[-1, 0]) == (200, 0, 0)
    # The run's history (its .wandb log) points at that file, by path and by hash.
    (log_file,) = run.glob("run-*.wandb")
    history = log_file.read_bytes()
    relative = gif.relative_to(run / "files").as_posix()
    assert f'"{relative}"'.encode() in history and b'"video-file"' in history
    assert hashlib.sha256(gif.read_bytes()).hexdigest().encode() in history
