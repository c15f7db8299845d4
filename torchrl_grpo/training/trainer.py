"""The training loop: collect -> advantage -> epochs of minibatch updates -> log -> eval -> save.

One :class:`Trainer` runs GRPO with snapshot branching, GRPO with episode groups,
or PPO, from a composed config (see ``conf/`` and :mod:`.config`). Frames count
every simulated env step: for GRPO, every branch step and every trunk step taken
to reach the decision points.

Ctrl-C (SIGINT) asks the loop to stop: the current iteration finishes, a
checkpoint is written, workers are shut down and :meth:`Trainer.train` returns
normally; a second Ctrl-C stops at once (the last periodic checkpoint stands).
"""

from __future__ import annotations

import copy
import json
import logging
import math
import random
import signal
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torch import nn
from torchrl.collectors import BaseCollector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase

from torchrl_grpo.branching import BRANCH_RETURN, GROUP_ID, MASK, plot_group
from torchrl_grpo.modules import EXPLORED
from torchrl_grpo.training.checkpoint import (
    get_rng_state,
    load_checkpoint,
    save_checkpoint,
    set_rng_state,
)
from torchrl_grpo.training.collect import (
    collector_state,
    env_frames,
    load_collector_state,
    make_collector,
)
from torchrl_grpo.training.config import check_config, to_container
from torchrl_grpo.training.env_builder import (
    episode_step_limit,
    make_env,
    make_layout,
    make_rollout_env,
)
from torchrl_grpo.training.evaluation import (
    BASELINE_LABELS,
    EvalResult,
    baseline_policy,
    evaluate,
    format_table,
    save_gif,
)
from torchrl_grpo.training.logging_builder import log_metrics, log_video, make_logger
from torchrl_grpo.training.loss_builder import (
    TRAIN_REWARD,
    is_grpo,
    make_advantage,
    make_loss,
    make_optimizer,
    make_reference_sync,
)
from torchrl_grpo.training.model_builder import make_base_policy, make_policy, make_value

__all__ = ["PhaseTimer", "TrainResult", "Trainer", "plot_learning_curve"]

log = logging.getLogger(__name__)

# Keys the updates read: everything else of a batch (states, positions) is dropped early.
_GRPO_KEYS = ("observation", "action", "action_log_prob", "advantage", MASK, GROUP_ID, "branch")


class PhaseTimer:
    """Wall-clock seconds per phase, accumulated until :meth:`pop`.

    Example:
        >>> timer = PhaseTimer()
        >>> with timer("collect"):
        ...     pass
        >>> sorted(timer.pop())
        ['time/collect']
    """

    def __init__(self) -> None:
        self._totals: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        """Time the ``with`` block as ``phase``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self._totals[phase] += time.perf_counter() - start

    def pop(self) -> dict[str, float]:
        """The accumulated times as ``time/<phase>`` metrics, then reset."""
        out = {f"time/{k}": v for k, v in self._totals.items()}
        self._totals.clear()
        return out


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

    Args:
        cfg: the composed config (``conf/config.yaml``).
        run_dir: where outputs go (default: ``experiment.out_dir`` or ``outputs/run``).

    Example:
        >>> from hydra import compose, initialize_config_dir
        >>> from torchrl_grpo.training import register_configs
        >>> import pathlib, tempfile, torchrl_grpo
        >>> conf = pathlib.Path(torchrl_grpo.__file__).parents[1] / "conf"
        >>> _ = register_configs()
        >>> with initialize_config_dir(str(conf), version_base=None):
        ...     cfg = compose("config", ["experiment=smoke", "logger=none",
        ...                              "experiment.total_frames=20",
        ...                              "experiment.final_eval_episodes=0"])
        >>> result = Trainer(cfg, run_dir=tempfile.mkdtemp()).train()
        >>> result.frames >= 20, result.checkpoint.name
        (True, 'last.pt')
    """

    def __init__(self, cfg: DictConfig, run_dir: str | Path | None = None) -> None:
        check_config(cfg)
        self.cfg = cfg
        self.config = to_container(cfg)
        out = run_dir or cfg.experiment.get("out_dir") or "outputs/run"
        self.run_dir = Path(out)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.seed = int(cfg.seed)
        _seed_everything(self.seed)
        self.grpo = is_grpo(cfg.algo)
        self.eval_env = make_env(cfg.env, seed=self.seed)
        self.layout = make_layout(self.eval_env)
        self.step_limit = episode_step_limit(self.eval_env, int(cfg.env.max_episode_steps))
        self.policy = make_policy(cfg.model, self.eval_env)
        self.value = None if self.grpo else make_value(cfg.model, self.eval_env)
        self.loss = make_loss(cfg.algo, self.policy, self.value)
        self.advantage = make_advantage(cfg.algo, self.value)
        self.ref_sync = make_reference_sync(cfg.algo, self.loss)
        self.optimizer = make_optimizer(cfg.optim, self.loss)
        self.tail_policy = (
            _make_tail_policy(cfg.algo, self.policy, self.eval_env) if self.grpo else None
        )
        self.replay = _make_replay(cfg.algo) if self.grpo else None
        self.iteration = 0
        self.frames = 0
        self.updates = 0
        # Seconds of training so far (resumed runs continue the count), and the start of
        # the iteration in progress: evaluation rows record the wall-clock they were at.
        self.wall_seconds = 0.0
        self._iteration_start: float | None = None
        self.eval_history: list[dict[str, float]] = []
        self._episode_acc: dict[str, Any] = {}
        self._collector_state: dict[str, Any] | None = None
        self._rng_state: dict[str, Any] | None = None
        self._stop_requested = False
        self._resumed_from: str | None = None
        if cfg.get("resume"):
            self._load(str(cfg.resume))
        name = f"{cfg.algo.name}_{cfg.env.name}_s{self.seed}"
        self.logger = make_logger(cfg.logger, self.run_dir, name, self.config)
        OmegaConf.save(cfg, self.run_dir / "config.yaml", resolve=True)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self, collector: BaseCollector) -> dict[str, Any]:
        """Everything needed to continue exactly (see :mod:`.checkpoint`)."""
        return {
            "version": 1,
            "config": self.config,
            "iteration": self.iteration,
            "frames": self.frames,
            "updates": self.updates,
            "wall_seconds": self.wall_seconds,
            "policy": self.policy.state_dict(),
            "tail_policy": None if self.tail_policy is None else self.tail_policy.state_dict(),
            "replay": None if self.replay is None else self.replay.state_dict(),
            "value": None if self.value is None else self.value.state_dict(),
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "ref_sync_counter": None if self.ref_sync is None else self.ref_sync.counter,
            "collector": collector_state(collector),
            "episode_acc": dict(self._episode_acc),
            "eval_history": list(self.eval_history),
            "rng": get_rng_state(),
        }

    def _load(self, path: str) -> None:
        ckpt = load_checkpoint(path)
        saved_algo = ckpt["config"]["algo"]["name"]
        if saved_algo != str(self.cfg.algo.name):
            raise ValueError(
                f"resume={path} was written by algo={saved_algo}, not algo={self.cfg.algo.name}"
            )
        # The parameters fit only the network they were trained in; a prior that changed
        # would load them silently into another policy.
        changed = _changed_keys(ckpt["config"]["model"], self.config["model"])
        if changed:
            raise ValueError(
                f"resume={path} was written with another model: "
                + ", ".join(f"model.{k}={a!r}, not {b!r}" for k, (a, b) in changed.items())
            )
        self.loss.load_state_dict(ckpt["loss"])
        self.policy.load_state_dict(ckpt["policy"])
        if self.tail_policy is not None and ckpt.get("tail_policy") is not None:
            self.tail_policy.load_state_dict(ckpt["tail_policy"])
        if self.replay is not None and ckpt.get("replay") is not None:
            saved = _replay_rows(OmegaConf.create(ckpt["config"]["algo"]))
            if saved != self.replay.storage.max_size:
                # A loaded storage keeps its saved size: the first write past it would fail.
                raise ValueError(
                    f"resume={path} replays {saved} trained steps and this config "
                    f"{self.replay.storage.max_size}: resume with the run's algo.replay_groups, "
                    "algo.group_size and algo.explore_steps"
                )
            self.replay.load_state_dict(ckpt["replay"])
        if self.value is not None and ckpt["value"] is not None:
            self.value.load_state_dict(ckpt["value"])
        self.optimizer.load_state_dict(ckpt["optimizer"])
        if self.ref_sync is not None and ckpt["ref_sync_counter"] is not None:
            self.ref_sync.counter = int(ckpt["ref_sync_counter"])
        self.iteration = int(ckpt["iteration"])
        self.frames = int(ckpt["frames"])
        self.updates = int(ckpt["updates"])
        self.wall_seconds = float(ckpt.get("wall_seconds", 0.0))
        self.eval_history = list(ckpt["eval_history"])
        self._episode_acc = dict(ckpt.get("episode_acc") or {})
        self._collector_state = ckpt["collector"]
        # Applied once the collector is built: building TorchRL's Collector runs the
        # policy once (to learn its outputs), which draws from torch's generator.
        self._rng_state = ckpt["rng"]
        self._resumed_from = path
        log.info("resumed from %s at iteration %d (%d frames)", path, self.iteration, self.frames)

    def save(self, collector: BaseCollector, name: str = "last.pt") -> Path:
        """Write a checkpoint into the run folder."""
        return save_checkpoint(self.state_dict(collector), self.run_dir / name)

    # ------------------------------------------------------------------ main loop
    def train(self) -> TrainResult:
        """Train until ``experiment.total_frames`` env steps (or Ctrl-C); evaluate; save."""
        cfg = self.cfg
        exp = cfg.experiment
        total = int(exp.total_frames)
        result = TrainResult(run_dir=self.run_dir)
        timer = PhaseTimer()
        # Installed before the workers fork: they inherit the handler, so Ctrl-C in a
        # terminal (SIGINT to the whole process group) cannot kill a worker mid-step.
        previous = signal.signal(signal.SIGINT, self._on_sigint)
        collector = None
        pbar = _progress(exp.progress_bar, total, self.frames)
        try:
            # PPO workers write their state after each step, so that a checkpoint can
            # restore them mid-episode (GRPO workers always ship states).
            extra = {} if self.grpo else {"return_state": True}
            env = None
            if str(cfg.rollout.backend) != "ray":
                # With the Ray backend every actor builds its own env workers.
                env = make_rollout_env(cfg.env, cfg.rollout, snapshots=self.grpo, **extra)
            collector = make_collector(
                cfg, env, self.policy, seed=self.seed, tail_policy=self.tail_policy
            )
            if self._collector_state is not None:
                load_collector_state(collector, self._collector_state)
            if self._rng_state is not None:
                set_rng_state(self._rng_state)
            start_frames = env_frames(collector)
            data_iter = iter(collector)
            while self.frames < total and not self._stop_requested:
                t0 = self._iteration_start = time.perf_counter()
                with timer("collect"):
                    batch = next(data_iter)
                frames_now = env_frames(collector)
                new_frames = frames_now - start_frames
                start_frames = frames_now
                self.frames += new_frames
                self.iteration += 1
                metrics = self._batch_metrics(batch)
                metrics.update(self._update(batch, timer))
                self._maybe_sync_tail()
                self._maybe_anneal_lr(total)
                if self._due(exp.plot_every) and self.grpo:
                    with timer("plot"):
                        self._plot_group(batch)
                if self._due(exp.eval_every) and exp.eval_episodes > 0:
                    with timer("eval"):
                        metrics.update(self._evaluate(int(exp.eval_episodes))[0])
                if self._due(exp.checkpoint_every) or self._stop_requested:
                    with timer("checkpoint"):
                        result.checkpoint = self.save(collector)
                times = timer.pop()
                elapsed = time.perf_counter() - t0
                self.wall_seconds += elapsed
                self._iteration_start = None
                metrics.update(times)
                metrics["time/iteration"] = elapsed
                metrics["time/fps"] = new_frames / max(times.get("time/collect", elapsed), 1e-9)
                metrics["time/total_fps"] = new_frames / max(elapsed, 1e-9)
                metrics["frames/total"] = self.frames
                metrics["frames/iteration"] = self.iteration
                metrics["frames/updates"] = self.updates
                log_metrics(self.logger, metrics, step=self.frames)
                if pbar is not None:
                    pbar.update(new_frames)
                    pbar.set_postfix(_postfix(metrics), refresh=False)
            result.checkpoint = self.save(collector)
        except KeyboardInterrupt:
            # A second Ctrl-C: stop now; the last periodic checkpoint stands.
            self._stop_requested = True
            log.warning("interrupted twice: stopping without a new checkpoint")
            last = self.run_dir / "last.pt"
            result.checkpoint = last if last.exists() else None
        finally:
            signal.signal(signal.SIGINT, previous)
            if collector is not None:
                collector.shutdown()
            if pbar is not None:
                pbar.close()
        result.interrupted = self._stop_requested
        result.frames, result.iterations = self.frames, self.iteration
        if not result.interrupted:
            self._final_evaluation(result)
        self._finish_logger(result)
        return result

    def _on_sigint(self, signum: int, frame: object) -> None:
        if self._stop_requested:
            raise KeyboardInterrupt
        self._stop_requested = True
        log.warning("Ctrl-C: finishing this iteration, saving a checkpoint, then stopping")

    def _due(self, every: int) -> bool:
        return every > 0 and self.iteration % every == 0

    # ------------------------------------------------------------------ metrics
    def _batch_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        if self.grpo:
            return _group_metrics(batch)
        return self._episode_metrics(batch)

    def _episode_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        """Returns and crashes of the episodes that ended in a PPO batch."""
        data = batch if batch.ndim == 2 else batch.unsqueeze(0)
        reward = data.get(("next", "reward")).reshape(data.shape)
        done = data.get(("next", "done")).reshape(data.shape)
        crashed = data.get(("next", "crashed")).reshape(data.shape)
        acc = self._episode_acc.get("return")
        acc = torch.zeros(data.shape[0]) if acc is None else acc.clone()
        returns, crashes = [], []
        for t in range(data.shape[1]):
            acc += reward[:, t]
            for w in done[:, t].nonzero().flatten().tolist():
                returns.append(float(acc[w]))
                crashes.append(bool(crashed[w, t]))
                acc[w] = 0.0
        self._episode_acc["return"] = acc
        out = {
            "train/speed": float(data.get(("next", "speed")).float().mean()),
            "train/reward": float(reward.float().mean()),
        }
        if returns:
            out["train/episode_return"] = float(np.mean(returns))
            out["train/crash_rate"] = float(np.mean(crashes))
            out["train/episodes"] = float(len(returns))
        return out

    # ------------------------------------------------------------------ updates
    def _update(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        if self.grpo:
            return self._update_grpo(batch, timer)
        return self._update_ppo(batch, timer)

    def _update_grpo(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        with timer("advantage"):
            bonus = self._bootstrap(batch)
            self.advantage(batch)
            data = batch.select(*_GRPO_KEYS, EXPLORED, strict=False).reshape(-1)
            train = data.get(MASK)
            if EXPLORED in data.keys():
                # Greedy-tail steps score the sampled ones; their actions were not sampled.
                train = train & data.get(EXPLORED)
            data = data[train]
        adv = data.get("advantage")
        stats = {
            "advantage/mean": float(adv.mean()),
            "advantage/std": float(adv.std()) if adv.numel() > 1 else 0.0,
            "advantage/abs_mean": float(adv.abs().mean()),
            "advantage/nonzero_fraction": float((adv != 0).float().mean()),
            "group/bootstrap_mean": bonus,
        }
        if self.replay is not None:
            data = self._replayed(data)
            stats["replay/steps"] = float(data.shape[0])
        if str(self.cfg.algo.get("action_weights", "uniform")) == "policy":
            data = _policy_weighted(data, int(self.eval_env.action_spec.n))
        with timer("update"):
            stats.update(self._epochs(data, advantage_fn=None))
        return stats

    def _replayed(self, data: TensorDictBase) -> TensorDictBase:
        """This batch's trained steps plus the replayed ones, log-probs of the current policy.

        With enumerated first actions and a scripted tail, a step's advantage compares
        every action under a fixed base policy: it does not depend on the policy that
        collected it, so old groups stay valid targets (DAgger's aggregated dataset).
        The "old" log-probs of the clipped ratio are the current policy's, so each
        update is a trust region around the policy it starts from.
        """
        self.replay.extend(data.exclude("action_log_prob"))
        data = self.replay[:]
        with torch.no_grad():
            dist = self.policy.get_dist(data.select(*self.policy.in_keys).clone())
            data.set("action_log_prob", dist.log_prob(data.get("action")))
        return data

    def _bootstrap(self, batch: TensorDictBase) -> float:
        """Write the training reward: the env's, plus a tail for branches cut by the horizon.

        A branch truncated by the horizon would go on collecting reward until its
        episode ends; a branch that crashed (terminated) would not. Without a critic,
        the tail is estimated as the batch's mean reward per valid step times the
        episode steps left. It is the same for every surviving branch of a group, so
        within the group it acts as the return a crash forfeits: without it, a crash
        late in a branch costs almost nothing and the policy learns to speed and crash.

        Returns:
            The mean tail added per branch.
        """
        mask = batch.get(MASK)
        reward = batch.get(("next", "reward"))
        train = reward.clone()
        batch.set(TRAIN_REWARD, train)
        if str(self.cfg.algo.get("bootstrap", "none")) != "batch_mean":
            return 0.0
        shape = mask.shape
        rate = float(reward.reshape(shape)[mask].mean())
        lengths = mask.sum(-1)
        last = (lengths - 1).clamp(min=0)
        terminated = batch.get(("next", "terminated")).reshape(shape)
        ended_by_env = terminated.gather(-1, last.unsqueeze(-1)).squeeze(-1)
        step_end = batch.get("root_step")[..., 0] + lengths
        left = (self.step_limit - step_end).clamp(min=0)
        tail = rate * left * (~ended_by_env & (lengths > 0))
        flat = train.view(*shape)
        flat.scatter_add_(-1, last.unsqueeze(-1), tail.unsqueeze(-1).to(flat.dtype))
        return float(tail.float().mean())

    def _update_ppo(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        data = batch.exclude("state", ("next", "state"))
        with timer("advantage"), torch.no_grad():
            self.advantage(data)
        adv = data.get("advantage")
        stats = {
            "advantage/mean": float(adv.mean()),
            "advantage/std": float(adv.std()),
            "advantage/abs_mean": float(adv.abs().mean()),
            "value/mean": float(data.get("state_value").mean()),
            "value/target_mean": float(data.get("value_target").mean()),
        }
        with timer("update"):
            stats.update(self._epochs(data.reshape(-1), advantage_fn=self.advantage, full=data))
        return stats

    def _epochs(
        self,
        data: TensorDictBase,
        advantage_fn: Any | None,
        full: TensorDictBase | None = None,
    ) -> dict[str, float]:
        """``algo.epochs`` passes of shuffled minibatches; mean of every loss output."""
        algo, optim = self.cfg.algo, self.cfg.optim
        n = data.shape[0]
        mb = min(int(algo.minibatch_size), n)
        sums: dict[str, float] = defaultdict(float)
        count = 0
        for epoch in range(int(algo.epochs)):
            if advantage_fn is not None and epoch > 0 and full is not None:
                # PPO recomputes GAE with the updated critic each epoch (sota-implementations).
                with torch.no_grad():
                    advantage_fn(full)
                data = full.reshape(-1)
            perm = torch.randperm(n)
            for start in range(0, n - mb + 1, mb):
                minibatch = data[perm[start : start + mb]]
                out = self.loss(minibatch)
                loss = sum(v for k, v in out.items() if k.startswith("loss_"))
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                grad_norm = torch.nn.utils.clip_grad_norm_(
                    [p for g in self.optimizer.param_groups for p in g["params"]],
                    float(optim.max_grad_norm),
                )
                self.optimizer.step()
                self.updates += 1
                if self.ref_sync is not None:
                    self.ref_sync.step()
                for key, value in out.items():
                    if isinstance(value, torch.Tensor) and value.numel() == 1:
                        sums[_metric_name(key)] += float(value.detach())
                sums["diag/grad_norm"] += float(grad_norm)
                sums["loss/total"] += float(loss.detach())
                count += 1
        out = {k: v / max(count, 1) for k, v in sums.items()}
        out["diag/lr"] = self.optimizer.param_groups[0]["lr"]
        out["diag/minibatches"] = float(count)
        return out

    def _maybe_sync_tail(self) -> None:
        """Copy the policy into the tail policy every ``algo.tail_sync_batches`` batches."""
        sync = self.cfg.algo.get("tail_sync_batches")
        if self.tail_policy is not None and sync is not None and self._due(int(sync)):
            self.tail_policy.load_state_dict(self.policy.state_dict())

    def _maybe_anneal_lr(self, total: int) -> None:
        if not self.cfg.optim.anneal_lr:
            return
        frac = max(0.0, 1.0 - self.frames / total)
        for group in self.optimizer.param_groups:
            group["lr"] = float(self.cfg.optim.lr) * frac

    # ------------------------------------------------------------------ media
    def _plot_group(self, batch: TensorDictBase) -> None:
        """Draw the group with the widest spread of returns (the most informative one)."""
        if not self.cfg.logger.group_plots:
            return
        returns = batch.get(BRANCH_RETURN)[:, :, 0, 0]
        group = int(returns.std(1).argmax())
        path = self.run_dir / "plots" / f"group_it{self.iteration:05d}.png"
        fig = plot_group(batch, group, path=path)
        log_video(self.logger, "media/branch_group", fig.video, step=self.frames)

    # ------------------------------------------------------------------ evaluation
    def _evaluate(self, episodes: int, record: bool = False) -> tuple[dict[str, float], EvalResult]:
        exp = self.cfg.experiment
        res, video = evaluate(
            self.eval_env,
            self.policy,
            episodes=episodes,
            seed=int(exp.eval_seed),
            max_steps=int(self.cfg.env.max_episode_steps),
            name=str(self.cfg.algo.name),
            record=self._render_env() if record else None,
        )
        summary = res.summary()
        wall = self.wall_seconds
        if self._iteration_start is not None:
            wall += time.perf_counter() - self._iteration_start
        row = {"iteration": self.iteration, "frames": self.frames, "wall_seconds": wall}
        self.eval_history.append({**row, **summary})
        with open(self.run_dir / "eval_history.jsonl", "a") as f:
            f.write(json.dumps(self.eval_history[-1]) + "\n")
        if video is not None:
            self._last_video = video
        metrics = {f"eval/{k}": v for k, v in summary.items() if k != "episodes"}
        return metrics, res

    def _render_env(self):
        if getattr(self, "_render", None) is None:
            self._render = make_env(self.cfg.env, render_mode="rgb_array")
        return self._render

    def _final_evaluation(self, result: TrainResult) -> None:
        exp = self.cfg.experiment
        episodes = int(exp.final_eval_episodes)
        self._last_video = None
        record = bool(self.cfg.logger.video)
        results: list[EvalResult] = []
        if episodes > 0:
            metrics, trained = self._evaluate(episodes, record=record)
            trained.name = f"{self.cfg.algo.name} (trained)"
            log_metrics(
                self.logger, {f"final/{k[5:]}": v for k, v in metrics.items()}, step=self.frames
            )
            summary = self.eval_history[-1]
            result.final = {k: v for k, v in summary.items() if k not in ("iteration",)}
            results.append(trained)
            n_actions = int(self.eval_env.action_spec.n)
            for name in exp.baselines:
                policy = baseline_policy(name, self.layout, n_actions, seed=self.seed)
                if policy is None:
                    log.warning("baseline %r does not apply to %s", name, self.cfg.env.scenario)
                    continue
                res, _ = evaluate(
                    self.eval_env,
                    policy,
                    episodes=episodes,
                    seed=int(exp.eval_seed),
                    max_steps=int(self.cfg.env.max_episode_steps),
                    name=BASELINE_LABELS.get(name, name),
                )
                results.append(res)
            table = format_table(results)
            result.results_table = self.run_dir / "results.md"
            result.results_table.write_text(
                f"{self.cfg.env.scenario}, {episodes} episodes from seed {exp.eval_seed}, "
                f"after {self.frames} env frames\n\n{table}\n"
            )
            result.results_json = self.run_dir / "results.json"
            result.results_json.write_text(
                json.dumps(
                    {"frames": self.frames, "results": [r.to_dict() for r in results]}, indent=1
                )
            )
            log.info("final evaluation:\n%s", table)
        if self._last_video is not None:
            result.video = save_gif(self._last_video, self.run_dir / "eval_episode.gif")
            log_video(self.logger, "media/eval_episode", self._last_video, step=self.frames)
        if self.eval_history:
            result.curve = plot_learning_curve(
                {str(self.cfg.algo.name): [self.eval_history]},
                self.run_dir / "learning_curve.png",
                title=f"{self.cfg.env.scenario}: deterministic evaluation",
            )

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


def _make_tail_policy(algo: DictConfig, policy: nn.Module, env: EnvBase) -> nn.Module | None:
    """The actor of greedy tails when it is not ``policy`` itself, or None.

    A scripted base policy (``algo.tail_policy``), or a frozen copy of ``policy``
    (``algo.tail_sync_batches``).
    """
    # check_config has refused both settings without explore_steps, and together.
    base = str(algo.get("tail_policy", "learner"))
    if base != "learner":
        return make_base_policy(base, env, "algo.tail_policy")
    if algo.get("tail_sync_batches") is None:
        return None
    tail = copy.deepcopy(policy)
    tail.requires_grad_(False)
    return tail


def _policy_weighted(data: TensorDictBase, n_actions: int) -> TensorDictBase:
    """Scale each enumerated step's advantage by ``n * pi(a|s)`` (``algo.action_weights``).

    The clipped surrogate is linear in the advantage, so this weighs each action's
    term by the probability the policy gives it: the sum over a group is then
    ``n`` times the expected surrogate over all actions of its root.
    """
    weight = n_actions * data.get("action_log_prob").exp()
    advantage = data.get("advantage")
    weighted = advantage * weight.reshape(advantage.shape)
    return data.clone(recurse=False).set("advantage", weighted)


def _make_replay(algo: DictConfig) -> ReplayBuffer | None:
    """The FIFO buffer of trained steps of ``algo.replay_groups`` groups, or None."""
    rows = _replay_rows(algo)
    return None if rows is None else ReplayBuffer(storage=LazyTensorStorage(rows), batch_size=None)


def _replay_rows(algo: DictConfig) -> int | None:
    """Trained steps the replay holds: one per explored step of each of the groups' branches."""
    groups = algo.get("replay_groups")
    if groups is None:
        return None
    return int(groups) * int(algo.group_size) * int(algo.explore_steps)


def _seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


def _changed_keys(saved: Any, current: Any, prefix: str = "") -> dict[str, tuple[Any, Any]]:
    """``{dotted key: (saved, current)}`` where two plain config trees differ.

    Only keys both trees hold are compared: a checkpoint written before a key existed
    ran with what is now its default.
    """
    if isinstance(saved, dict) and isinstance(current, dict):
        out: dict[str, tuple[Any, Any]] = {}
        for key in sorted(saved.keys() & current.keys()):
            out |= _changed_keys(saved.get(key), current.get(key), f"{prefix}{key}.")
        return out
    return {} if saved == current else {prefix.rstrip("."): (saved, current)}


def _progress(enabled: bool, total: int, initial: int):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=min(initial, total), unit="frames", dynamic_ncols=True)


def _postfix(metrics: dict[str, float]) -> dict[str, str]:
    keys = {
        "eval/return": "eval",
        "eval/crash_rate": "crash",
        "group/return_mean": "group_ret",
        "train/episode_return": "ep_ret",
        "loss/objective": "loss",
        "time/fps": "fps",
    }
    return {short: f"{metrics[k]:.3g}" for k, short in keys.items() if k in metrics}


def _metric_name(key: str) -> str:
    if key.startswith("loss_"):
        return f"loss/{key[5:]}"
    return f"diag/{key}"


def _group_metrics(batch: TensorDictBase) -> dict[str, float]:
    """Statistics of a ``[R, G, T]`` batch of branch groups."""
    mask = batch.get(MASK)
    returns = batch.get(BRANCH_RETURN)[:, :, 0, 0].double()
    lengths = mask.sum(-1).double()
    crashed = (batch.get(("next", "crashed")).reshape(mask.shape) & mask).any(-1)
    speed = batch.get(("next", "speed")).reshape(mask.shape)[mask]
    std = returns.std(1) if returns.shape[1] > 1 else torch.zeros(returns.shape[0])
    return {
        "group/return_mean": float(returns.mean()),
        "group/return_std": float(std.mean()),
        "group/zero_std_fraction": float((std == 0).double().mean()),
        "group/best_minus_mean": float((returns.max(1).values - returns.mean(1)).mean()),
        "group/crash_spread": float((crashed.any(1) & ~crashed.all(1)).double().mean()),
        "train/branch_return": float(returns.mean()),
        "train/branch_length": float(lengths.mean()),
        "train/crash_rate": float(crashed.double().mean()),
        "train/speed": float(speed.float().mean()) if speed.numel() else math.nan,
        "train/reward": float(
            batch.get(("next", "reward")).reshape(mask.shape)[mask].float().mean()
        ),
    }


def plot_learning_curve(
    runs: dict[str, list[list[dict[str, float]]]],
    path: str | Path,
    *,
    metric: str = "return",
    title: str | None = None,
    hlines: dict[str, float] | None = None,
) -> Path:
    """Plot ``metric`` against frames: one line per label, mean ± std over its runs.

    Args:
        runs: ``{label: [history of run 1, history of run 2, ...]}``, each history a
            list of ``{"frames": ..., metric: ...}`` rows (``eval_history.jsonl``).
        path: PNG to write.
        metric: the key to plot.
        title: figure title.
        hlines: horizontal reference lines ``{label: value}`` (baselines).

    Example:
        >>> import tempfile
        >>> h = [{"frames": 0, "return": 1.0}, {"frames": 10, "return": 2.0}]
        >>> plot_learning_curve({"a": [h, h]}, tempfile.mkdtemp() + "/c.png").suffix
        '.png'
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for label, histories in runs.items():
        # At equal frames keep the last row: the final evaluation (more episodes).
        histories = [list({r["frames"]: r for r in h}.values()) for h in histories if h]
        if not histories:
            continue
        grid = np.unique(np.concatenate([[r["frames"] for r in h] for h in histories]))
        curves = np.stack(
            [np.interp(grid, [r["frames"] for r in h], [r[metric] for r in h]) for h in histories]
        )
        mean, std = curves.mean(0), curves.std(0)
        line = ax.plot(
            grid, mean, label=f"{label} ({len(histories)} run{'s' if len(histories) > 1 else ''})"
        )[0]
        if len(histories) > 1:
            ax.fill_between(grid, mean - std, mean + std, color=line.get_color(), alpha=0.2)
    for label, value in (hlines or {}).items():
        ax.axhline(value, ls="--", lw=1, color="gray")
        ax.text(ax.get_xlim()[0], value, f" {label}", va="bottom", fontsize=8, color="gray")
    ax.set_xlabel("env frames (every branch and trunk step)")
    ax.set_ylabel(f"evaluation {metric}")
    if title:
        ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
