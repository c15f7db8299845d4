"""Metrics reach the logger as one row per training iteration."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from torchrl_grpo.training import log_metrics, make_logger


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
        log_metrics(logger, {"train/a": 1.0, "train/b": 2.0, "loss/c": 3.0}, step=10)
        log_metrics(logger, {"train/a": 4.0, "train/b": 5.0, "loss/c": 6.0}, step=20)
    finally:
        logger.experiment.finish()
    assert len(rows) == 2
    for row, expected in zip(rows, ((1.0, 2.0, 3.0), (4.0, 5.0, 6.0)), strict=True):
        assert tuple(row[k] for k in ("train/a", "train/b", "loss/c")) == expected


def test_csv_logger_writes_every_metric_at_its_step(tmp_path):
    logger = make_logger(OmegaConf.create({"backend": "csv"}), tmp_path, "csv", {"seed": 0})
    log_metrics(logger, {"train/a": 1.5, "train/none": None}, step=7)
    files = list((tmp_path / "csv").rglob("a.csv"))
    assert len(files) == 1 and files[0].read_text().strip() == "7,1.5"
    assert not list((tmp_path / "csv").rglob("none.csv"))
