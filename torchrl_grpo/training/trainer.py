"""The training loop: collect -> update -> hooks (plot, evaluate, save) -> log, until the budget.

One :class:`Trainer` runs any registered algorithm (:mod:`~torchrl_grpo.training.algos`:
GRPO with snapshot branching, GRPO with episode groups, PPO) from a composed config
(see ``conf/`` and :mod:`.config`). Frames count every simulated env step: for GRPO,
every branch step and every trunk step taken to reach the decision points.

Ctrl-C (SIGINT) asks the loop to stop: the current iteration finishes, a
checkpoint is written, workers are shut down and :meth:`Trainer.train` returns
normally; a second Ctrl-C stops at once (the last periodic checkpoint stands).
"""

from __future__ import annotations

import logging
import os
import random
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torchrl.collectors import BaseCollector

from torchrl_grpo.training.algos.registry import algorithm_for
from torchrl_grpo.training.averaging import PolicyAverage
from torchrl_grpo.training.checkpoint import (
    Progress,
    check_resumable,
    checkpoint_dict,
    load_checkpoint,
    save_checkpoint,
    set_rng_state,
)
from torchrl_grpo.training.collect import (
    collector_state,
    env_frames,
    load_collector_state,
    world_steps,
)
from torchrl_grpo.training.config import check_config, to_container, typed_config
from torchrl_grpo.training.env_builder import check_device, make_env
from torchrl_grpo.training.hooks import Hook, default_hooks
from torchrl_grpo.training.logging_builder import log_metrics, make_logger
from torchrl_grpo.training.metrics import PhaseTimer, progress_bar, progress_postfix
from torchrl_grpo.training.model_builder import make_policy
from torchrl_grpo.training.optim_builder import anneal_lr
from torchrl_grpo.training.pretrained import init_policy
from torchrl_grpo.training.resolvers import env_name
from torchrl_grpo.training.run_plots import plot_learning_curve

# PhaseTimer and plot_learning_curve lived here before metrics.py and plots.py: still
# importable from here.
__all__ = ["PhaseTimer", "TrainResult", "Trainer", "plot_learning_curve", "seed_everything"]

log = logging.getLogger(__name__)


@dataclass
class TrainResult:
    """Where a run left its outputs, and its final evaluation.

    Attributes:
        run_dir: the run folder.
        checkpoint: the last checkpoint.
        results_table: Markdown table of the final evaluation (``results.md``).
        results_json: per-episode results (``results.json``).
        curve: learning-curve plot (``learning_curve.png``).
        video: GIF of the first final-evaluation episode, if recorded.
        logs: the logger's folder (``None`` without a logger).
        frames: env frames simulated.
        iterations: training iterations done.
        interrupted: the run was stopped by Ctrl-C.
        final: the final evaluation's summary.

    Example:
        >>> run_dir = Path("outputs/run")
        >>> result = TrainResult(run_dir, checkpoint=run_dir / "last.pt", frames=2048,
        ...                      iterations=4, final={"return": 21.5})
        >>> status = "interrupted (Ctrl-C)" if result.interrupted else "done"
        >>> print(f"{status}: {result.frames} env frames, {result.iterations} iterations, "
        ...       f"return {result.final['return']:.2f}, checkpoint {result.checkpoint.name}")
        done: 2048 env frames, 4 iterations, return 21.50, checkpoint last.pt
    """

    run_dir: Path
    checkpoint: Path | None = None
    results_table: Path | None = None
    results_json: Path | None = None
    curve: Path | None = None
    video: Path | None = None
    logs: Path | None = None
    frames: int = 0
    iterations: int = 0
    interrupted: bool = False
    final: dict[str, float] = field(default_factory=dict)


class Trainer:
    """Builds everything from a composed config and runs :meth:`train`.

    The policy is built here, everything the algorithm of ``algo.name`` needs by the
    algorithm (:attr:`algo`); evaluation, plots and checkpoints are :attr:`hooks`.

    Args:
        cfg: the composed config (``conf/config.yaml``).
        run_dir: where outputs go (default: ``experiment.out_dir`` or ``outputs/run``).
        hooks: more hooks, run after the default ones
            (:func:`~torchrl_grpo.training.hooks.default_hooks`).

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training import Hook, compose_config
        >>> class CountBatches(Hook):
        ...     def __init__(self):
        ...         self.batches = 0
        ...     def due(self, trainer, batch):
        ...         return True
        ...     def on_iteration(self, trainer, batch, result):
        ...         self.batches += 1
        ...         return {}
        >>> cfg = compose_config(["experiment=smoke", "logger=none", "experiment.total_frames=20",
        ...                       "experiment.final_eval_episodes=0"])
        >>> counter = CountBatches()
        >>> result = Trainer(cfg, run_dir=tempfile.mkdtemp(), hooks=[counter]).train()
        >>> result.frames >= 20, result.checkpoint.name, counter.batches == result.iterations
        (True, 'last.pt', True)
    """

    def __init__(
        self, cfg: DictConfig, run_dir: str | Path | None = None, hooks: Sequence[Hook] = ()
    ) -> None:
        check_config(cfg)
        # What the user composed is saved and logged; the run executes it with the
        # settings its algorithm fixes filled in.
        self.config = to_container(cfg)
        composed = cfg
        cfg = algorithm_for(cfg.algo).with_fixed_settings(cfg)
        self.cfg = cfg
        self.run_dir = Path(run_dir or cfg.experiment.get("out_dir") or "outputs/run")
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.seed = int(cfg.seed)
        seed_everything(self.seed)
        device = check_device(str(cfg.get("device", "cpu")))
        self.eval_env = make_env(cfg.env, seed=self.seed)
        # Built on the evaluation env (a CPU env), then moved to where the rollouts and
        # the learner run: evaluations drive a CPU copy (hooks.EvaluationHook).
        self.policy = make_policy(cfg.model, self.eval_env).to(device)
        if cfg.get("init_from") and not cfg.get("resume"):
            # Before the algorithm: a reference policy and the weight average copy these.
            init_policy(str(cfg.init_from), self.policy, cfg)
        self.algo = algorithm_for(cfg.algo)(cfg, self.policy, self.eval_env)
        decay = cfg.optim.get("ema_decay")
        self.average = None if decay is None else PolicyAverage(self.policy, float(decay))
        self.hooks: list[Hook] = [*default_hooks(), *hooks]
        self.progress = Progress()
        self.collector: BaseCollector | None = None
        self.stop_requested = False
        #: A progress bar over frames, on a terminal (a pipeline of runs shows its own).
        self.show_progress = sys.stderr.isatty()
        # Env workers fork with the SIGINT handler: only this process acts on it.
        self._pid = os.getpid()
        self._iteration_start: float | None = None
        # What a resumed run restores once its collector is built (see train()).
        self._collector_state: dict[str, Any] | None = None
        self._rng_state: dict[str, Any] | None = None
        if cfg.get("resume"):
            self._load(str(cfg.resume))
        name = f"{cfg.algo.name}_{env_name(cfg.env.scenario)}_s{self.seed}"
        self.logger = make_logger(cfg.logger, self.run_dir, name, self.config)
        OmegaConf.save(composed, self.run_dir / "config.yaml", resolve=True)

    @property
    def iteration(self) -> int:
        """Training iterations done."""
        return self.progress.iteration

    @property
    def eval_policy(self) -> nn.Module:
        """The policy evaluated and saved: the average (``optim.ema_decay``), or the live one."""
        return self.policy if self.average is None else self.average.module

    @property
    def frames(self) -> int:
        """Env frames simulated."""
        return self.progress.frames

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self, collector: BaseCollector | None = None) -> dict[str, Any]:
        """Everything needed to continue exactly (see :mod:`.checkpoint`)."""
        ckpt = checkpoint_dict(
            self.config,
            self.progress,
            self.eval_policy.state_dict(),
            self.algo.state_dict(),
            collector_state(collector or self.collector),
        )
        if self.average is not None:
            # "policy" is the average, what evaluate.py drives; the live weights go beside.
            ckpt["policy_average"] = self.average.state_dict()
        return ckpt

    def save(self, collector: BaseCollector | None = None, name: str = "last.pt") -> Path:
        """Write a checkpoint into the run folder."""
        return save_checkpoint(self.state_dict(collector), self.run_dir / name)

    def _load(self, path: str) -> None:
        ckpt = load_checkpoint(path)
        saved = to_container(typed_config(ckpt["config"]))
        check_resumable(path, saved, self.config)
        self.algo.load_state_dict(ckpt, source=path)
        average = ckpt.get("policy_average")
        if self.average is not None:
            self.average.load_state_dict(ckpt["policy"], average)
        else:
            # Averaging switched off: train on from the live weights, not the average.
            live = ckpt["policy"] if average is None else average["train_policy"]
            self.policy.load_state_dict(live)
        self.progress = Progress.from_checkpoint(ckpt)
        self._collector_state = ckpt["collector"]
        # Applied once the collector is built: building TorchRL's Collector runs the
        # policy once (to learn its outputs), which draws from torch's generator.
        self._rng_state = ckpt["rng"]
        log.info("resumed from %s at iteration %d (%d frames)", path, self.iteration, self.frames)
        threads = ckpt.get("threads")  # absent from checkpoints before 2026-12-04
        if threads is not None and threads != torch.get_num_threads():
            # Sums split over another number of threads round differently: the run goes
            # on, but not as the uninterrupted run would have.
            log.warning(
                "%s was trained with %d torch threads and resumes with %d: it will not "
                "continue bit for bit (OMP_NUM_THREADS=%d or torch.set_num_threads(%d) would)",
                path,
                threads,
                torch.get_num_threads(),
                threads,
                threads,
            )

    # ------------------------------------------------------------------ main loop
    def train(self) -> TrainResult:
        """Train until ``experiment.total_frames`` env steps (or Ctrl-C); evaluate; save."""
        exp = self.cfg.experiment
        total = int(exp.total_frames)
        result = TrainResult(run_dir=self.run_dir)
        timer = PhaseTimer()
        # Installed before the workers fork: they inherit the handler, so Ctrl-C in a
        # terminal (SIGINT to the whole process group) cannot kill a worker mid-step.
        previous = signal.signal(signal.SIGINT, self._on_sigint)
        pbar = progress_bar(self.show_progress, total, self.frames)
        self.collector = None
        try:
            # Before the collector: building it runs the policy once (a random draw).
            for hook in self.hooks:
                hook.on_train_start(self, result)
            self.collector = collector = self.algo.make_collector(self.seed)
            if self._collector_state is not None:
                load_collector_state(collector, self._collector_state)
            if self._rng_state is not None:
                set_rng_state(self._rng_state)
            start_frames = env_frames(collector)
            start_worlds = world_steps(collector)
            data_iter = iter(collector)
            while self.frames < total and not self.stop_requested:
                t0 = self._iteration_start = time.perf_counter()
                with timer("collect"):
                    batch = next(data_iter)
                frames_now = env_frames(collector)
                new_frames, start_frames = frames_now - start_frames, frames_now
                self.progress.frames += new_frames
                self.progress.iteration += 1
                metrics = self.algo.batch_metrics(batch)
                metrics.update(self.algo.update(batch, timer))
                self.algo.after_batch(self.iteration)
                if self.average is not None:
                    self.average.update()
                anneal_lr(self.algo.optimizer, self.cfg.optim, self.frames, total)
                for hook in self.hooks:
                    if hook.due(self, batch):
                        with timer(hook.phase):
                            metrics.update(hook.on_iteration(self, batch, result))
                times = timer.pop()
                elapsed = time.perf_counter() - t0
                self.progress.wall_seconds += elapsed
                self._iteration_start = None
                metrics.update(times)
                metrics["time/iteration"] = elapsed
                metrics["time/fps"] = new_frames / max(times.get("time/collect", elapsed), 1e-9)
                metrics["time/total_fps"] = new_frames / max(elapsed, 1e-9)
                worlds_now = world_steps(collector)
                if worlds_now is not None and start_worlds is not None:
                    # The simulator's own throughput: every row it stepped, masked or not.
                    collect_time = max(times.get("time/collect", elapsed), 1e-9)
                    metrics["time/env_steps_per_s"] = (worlds_now - start_worlds) / collect_time
                    start_worlds = worlds_now
                metrics["collect/frames"] = self.frames
                metrics["train/iteration"] = self.iteration
                metrics["train/updates"] = self.algo.updates
                log_metrics(self.logger, metrics, step=self.frames)
                if pbar is not None:
                    pbar.update(new_frames)
                    pbar.set_postfix(progress_postfix(metrics), refresh=False)
            for hook in self.hooks:
                hook.on_loop_end(self, result)
        except KeyboardInterrupt:
            # A second Ctrl-C: stop now; the last periodic checkpoint stands.
            self.stop_requested = True
            log.warning("interrupted twice: stopping without a new checkpoint")
            last = self.run_dir / "last.pt"
            result.checkpoint = last if last.exists() else None
        finally:
            signal.signal(signal.SIGINT, previous)
            if self.collector is not None:
                self.collector.shutdown()
                self.collector = None
            if pbar is not None:
                pbar.close()
        result.interrupted = self.stop_requested
        result.frames, result.iterations = self.frames, self.iteration
        if not result.interrupted:
            for hook in self.hooks:
                hook.on_train_end(self, result)
        self._finish_logger(result)
        return result

    def wall_seconds(self) -> float:
        """Seconds of training so far (a resumed run's included), the iteration in progress too."""
        wall = self.progress.wall_seconds
        if self._iteration_start is not None:
            wall += time.perf_counter() - self._iteration_start
        return wall

    def _on_sigint(self, signum: int, frame: object) -> None:
        if os.getpid() != self._pid:
            return  # a forked env worker: the trainer stops it, one warning is enough
        if self.stop_requested:
            raise KeyboardInterrupt
        self.stop_requested = True
        log.warning("Ctrl-C: finishing this iteration, saving a checkpoint, then stopping")

    def _finish_logger(self, result: TrainResult) -> None:
        if self.logger is None:
            return
        result.logs = Path(getattr(self.logger, "log_dir", None) or self.run_dir)
        experiment = getattr(self.logger, "experiment", None)
        finish = getattr(experiment, "finish", None)
        if callable(finish):
            finish()
            run_dir = getattr(experiment, "dir", None)
            if run_dir:
                # wandb's files/ folder; its parent is the run folder `wandb sync` takes.
                result.logs = Path(run_dir).parent


def seed_everything(seed: int) -> None:
    """Seed torch, numpy and Python's ``random``.

    Example:
        >>> seed_everything(0); a = torch.rand(1)
        >>> seed_everything(0); bool(torch.rand(1) == a)
        True
    """
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
