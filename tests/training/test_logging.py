"""Metrics reach the logger as one row per training iteration."""

from __future__ import annotations

import json

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


def test_each_iteration_is_one_wandb_row_keyed_by_frames(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from conftest import TINY, compose_config

    from torchrl_grpo.training import Trainer

    monkeypatch.setenv("WANDB_SILENT", "true")
    cfg = compose_config(
        [
            *TINY,
            "logger=wandb",
            "logger.video=true",
            "experiment.eval_every=1",
            "experiment.plot_every=1",
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
    # One row per iteration, then the final evaluation's.
    assert result.iterations >= 2 and len(rows) == result.iterations + 1, [sorted(r) for r in rows]
    history = [json.loads(line) for line in (tmp_path / "run" / "eval_history.jsonl").open()]
    # Each row names its seed set: the periodic one, then the final one.
    exp = cfg.experiment
    assert [h["seed"] for h in history] == [exp.eval_seed] * result.iterations + [
        exp.final_eval_seed
    ]
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
