"""Builder of the ``logger`` group: TorchRL's wandb (offline by default) or CSV logger.

Metric names live in stable namespaces (CleanRL style): ``train/`` (what the
collected data shows), ``group/`` (branch-group statistics), ``loss/`` (every loss
term), ``diag/`` (clip fraction, KL, ESS, entropy, ratios, gradient norm),
``advantage/``, ``eval/`` (deterministic evaluation), ``time/`` (seconds per phase,
frames per second) and ``frames/``. The step of every metric is the number of env
frames simulated so far, branch and trunk steps included.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from pathlib import Path
from typing import Any, Literal, get_args

import torch
from omegaconf import DictConfig
from torchrl.record.loggers import CSVLogger, Logger, WandbLogger

__all__ = ["LoggerKind", "WandbRunMode", "log_hparams", "log_metrics", "log_video", "make_logger"]

log = logging.getLogger(__name__)

#: Where metrics go (``logger.backend``): TorchRL's wandb or CSV logger, or nowhere.
LoggerKind = Literal["wandb", "csv", "none"]
#: wandb's mode (``logger.mode``): ``offline`` writes a run folder to ``wandb sync`` later.
WandbRunMode = Literal["offline", "online"]


def make_logger(
    logger_cfg: DictConfig, run_dir: str | Path, exp_name: str, config: dict
) -> Logger | None:
    """The TorchRL logger of ``logger.backend``; ``None`` for ``none``.

    ``wandb`` with ``mode: offline`` sets ``WANDB_MODE=offline`` and needs no
    network: the run lands in ``<run_dir>/wandb/offline-run-*``, to upload later
    with ``wandb sync <that folder>``.

    Args:
        logger_cfg: the ``logger`` group.
        run_dir: the run folder.
        exp_name: the experiment (run) name.
        config: the resolved config, logged as hyper-parameters.

    Example:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"backend": "csv"})
        >>> logger = make_logger(cfg, tempfile.mkdtemp(), "demo", {"seed": 0})
        >>> type(logger).__name__
        'CSVLogger'
    """
    backend = str(logger_cfg.backend)
    run_dir = Path(run_dir)
    if backend == "none":
        return None
    if backend == "csv":
        logger: Logger = CSVLogger(exp_name, log_dir=str(run_dir / "csv"), video_format="pt")
    elif backend == "wandb":
        offline = str(logger_cfg.get("mode", "offline")) == "offline"
        if offline:
            # Set before wandb starts: no login prompt, no network access.
            os.environ["WANDB_MODE"] = "offline"
        logger = WandbLogger(
            exp_name,
            offline=offline,
            save_dir=str(run_dir),
            project=logger_cfg.get("project"),
            group=logger_cfg.get("group"),
            tags=list(logger_cfg.get("tags") or []),
            config=config,
            log_env_packages=False,
        )
    else:
        raise ValueError(
            f"logger.backend must be one of {', '.join(get_args(LoggerKind))}, got {backend!r}"
        )
    log_hparams(logger, config)
    return logger


def log_hparams(logger: Logger | None, config: dict) -> None:
    """Log the resolved config (CSV: ``hparams.txt``; wandb: the run config)."""
    if logger is None:
        return
    try:
        logger.log_hparams(config)
    except Exception:  # a logging failure must not stop training
        log.warning("could not log the config", exc_info=True)


def log_metrics(logger: Logger | None, metrics: dict[str, Any], step: int) -> None:
    """Log scalars under their names at ``step``, in one call of TorchRL's ``log_metrics``.

    One call, so that wandb records one history row per training iteration (a
    ``log_scalar`` per metric would commit a row each).

    Example:
        >>> log_metrics(None, {"train/return": 1.0}, step=0)  # no logger: a no-op
    """
    if logger is None:
        return
    clean = {}
    for name, value in metrics.items():
        if isinstance(value, torch.Tensor):
            value = value.detach().float().mean().item()
        if value is None:
            continue
        clean[name] = float(value)
    logger.log_metrics(clean, step=step)


def log_video(logger: Logger | None, name: str, video: torch.Tensor, step: int) -> None:
    """Log a ``(1, T, 3, H, W)`` uint8 video; skipped when the backend cannot encode it.

    wandb encodes videos with moviepy (the ``dev`` extra); without it the video is
    skipped with a warning (the GIF in the run folder is always written).

    Example:
        >>> import os, tempfile
        >>> from omegaconf import OmegaConf
        >>> run_dir = tempfile.mkdtemp()
        >>> logger = make_logger(OmegaConf.create({"backend": "csv"}), run_dir, "demo", {})
        >>> video = torch.zeros(1, 4, 3, 8, 8, dtype=torch.uint8)  # four black 8x8 frames
        >>> log_video(logger, "eval/video", video, step=0)
        >>> os.listdir(os.path.join(run_dir, "csv", "demo", "videos", "eval"))
        ['video_0.pt']
        >>> log_video(None, "eval/video", video, step=0)  # no logger: a no-op
    """
    if logger is None:
        return
    if isinstance(logger, WandbLogger) and importlib.util.find_spec("moviepy") is None:
        log.warning("moviepy is not installed: video %s not sent to wandb", name)
        return
    try:
        logger.log_video(name, video, step=step)
    except Exception:  # media are a convenience: never lose a run over them
        log.warning("could not log video %s", name, exc_info=True)
