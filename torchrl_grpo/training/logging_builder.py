"""Builder of the ``logger`` group: TorchRL's wandb (offline by default) or CSV logger.

Metric names live in four namespaces (CleanRL style): ``collect/`` (what the collected
data shows: returns, crashes, speed, branch-group statistics, frames), ``train/`` (the
update: every loss term as ``loss_*``, clip fraction, KL, ESS, entropy, ratios,
gradient norm, learning rate, advantages), ``eval/`` (deterministic evaluation; the
final one as ``eval/final_*``) and ``time/`` (seconds per phase, frames per second).
An iteration's metrics, its media included, are one row (one ``wandb.log`` call),
keyed by the number of env frames simulated so far, branch and trunk steps included.
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path
from typing import Any, Literal, get_args

import torch
from omegaconf import DictConfig
from torchrl.record.loggers import CSVLogger, Logger, WandbLogger

from torchrl_grpo.training.run_plots import save_gif

__all__ = [
    "LoggerKind",
    "is_video",
    "log_hparams",
    "log_metrics",
    "log_video",
    "make_logger",
]

log = logging.getLogger(__name__)

#: Where metrics go (``logger.backend``): TorchRL's wandb logger offline (a run folder to
#: ``wandb sync`` later) or online, its CSV logger, or nowhere.
LoggerKind = Literal["wandb", "wandb_online", "csv", "none"]


def make_logger(
    logger_cfg: DictConfig, run_dir: str | Path, exp_name: str, config: dict
) -> Logger | None:
    """The TorchRL logger of ``logger.backend``; ``None`` for ``none``.

    ``wandb`` sets ``WANDB_MODE=offline`` and needs no network: the run lands in
    ``<run_dir>/wandb/offline-run-*``, to upload later with ``wandb sync <that folder>``;
    ``wandb_online`` streams it. The project is ``WANDB_PROJECT`` (``torchrl_grpo``
    when unset).

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
    elif backend in ("wandb", "wandb_online"):
        offline = backend == "wandb"
        if offline:
            # Set before wandb starts: no login prompt, no network access.
            os.environ["WANDB_MODE"] = "offline"
        logger = WandbLogger(
            exp_name,
            offline=offline,
            save_dir=str(run_dir),
            project=os.environ.get("WANDB_PROJECT", "torchrl_grpo"),
            # wandb reads WANDB_RUN_GROUP and WANDB_TAGS from the environment itself.
            group=os.environ.get("WANDB_RUN_GROUP"),
            tags=[t for t in os.environ.get("WANDB_TAGS", "").split(",") if t],
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


def is_video(value: Any) -> bool:
    """Whether a metric's value is a video: a ``(1, T, 3, H, W)`` uint8 tensor.

    Example:
        >>> is_video(torch.zeros(1, 4, 3, 8, 8, dtype=torch.uint8)), is_video(torch.ones(3))
        (True, False)
    """
    return isinstance(value, torch.Tensor) and value.dtype == torch.uint8 and value.dim() == 5


def log_metrics(logger: Logger | None, metrics: dict[str, Any], step: int) -> None:
    """Log an iteration's metrics at ``step`` (env frames): one row, videos included.

    Scalars (numbers, tensors averaged; ``None`` skipped) and videos (:func:`is_video`)
    go to wandb in one ``wandb.log`` call, so that a run's history has one row per
    training iteration, keyed by frames (TorchRL's logger sets each namespace's
    ``<namespace>/step`` to ``step``). The CSV logger writes a file per metric and per
    video.

    Example:
        >>> log_metrics(None, {"train/loss_objective": 1.0}, step=0)  # no logger: a no-op
    """
    if logger is None:
        return
    scalars, videos = {}, {}
    for name, value in metrics.items():
        if is_video(value):
            videos[name] = value
            continue
        if isinstance(value, torch.Tensor):
            value = value.detach().float().mean().item()
        if value is None:
            continue
        scalars[name] = float(value)
    if not isinstance(logger, WandbLogger):
        logger.log_metrics(scalars, step=step)
        for name, video in videos.items():
            log_video(logger, name, video, step=step)
        return
    row: dict[str, Any] = dict(scalars)
    # wandb copies a video file into the run's media folder when it is logged: the
    # GIFs may go with the temporary folder.
    with tempfile.TemporaryDirectory() as tmp:
        for name, video in videos.items():
            media = _wandb_video(video, Path(tmp) / f"{name.replace('/', '_')}.gif", logger)
            if media is not None:
                row[name] = media
        logger.log_metrics(row, step=step)


def _wandb_video(video: torch.Tensor, path: Path, logger: WandbLogger) -> Any:
    """A ``wandb.Video`` of a GIF written with Pillow: wandb needs moviepy only for arrays."""
    import wandb

    try:
        save_gif(video.cpu(), path, fps=int(logger.video_fps))
        return wandb.Video(str(path))
    except Exception:  # media are a convenience: never lose a run over them
        log.warning("could not write video %s for wandb", path.stem, exc_info=True)
        return None


def log_video(logger: Logger | None, name: str, video: torch.Tensor, step: int) -> None:
    """Log a ``(1, T, 3, H, W)`` uint8 video.

    wandb gets a GIF written with Pillow (a default dependency, no moviepy needed), in
    its own row at ``step``; the CSV logger a ``.pt`` file.

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
    if isinstance(logger, WandbLogger):
        log_metrics(logger, {name: video}, step=step)
        return
    try:
        logger.log_video(name, video, step=step)
    except Exception:  # media are a convenience: never lose a run over them
        log.warning("could not log video %s", name, exc_info=True)
