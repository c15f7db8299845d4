"""The side jobs of the training loop, as hooks: evaluation, plots, checkpoints.

A :class:`Hook` is called by the :class:`~torchrl_grpo.training.Trainer` at four
points: before the first batch (:meth:`~Hook.on_train_start`), after each iteration's
update when it is :meth:`~Hook.due` (timed as its
``phase``, its metrics logged with the iteration's), once the loop has ended while the
collector still runs (:meth:`~Hook.on_loop_end`), and when training is done and not
interrupted (:meth:`~Hook.on_train_end`). :func:`default_hooks` are the trainer's;
pass more with ``Trainer(cfg, hooks=[...])`` (BenchMARL's callbacks).
"""

from __future__ import annotations

import copy
import json
import logging
import sys
from pathlib import Path
from typing import Any, Protocol

from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from torchrl_grpo.branching.group_plots import plot_group
from torchrl_grpo.branching.keys import BRANCH_RETURN
from torchrl_grpo.training.baselines import evaluate_baselines
from torchrl_grpo.training.checkpoint import (
    Progress,
    get_rng_state,
    save_checkpoint,
    set_rng_state,
)
from torchrl_grpo.training.config import records_video
from torchrl_grpo.training.env_builder import make_env, tensor_covers
from torchrl_grpo.training.eval_episodes import eval_workers
from torchrl_grpo.training.evaluation import evaluate
from torchrl_grpo.training.logging_builder import log_metrics
from torchrl_grpo.training.results import EvalResult, format_table, paired_verdicts
from torchrl_grpo.training.run_plots import plot_run_curve, save_gif
from torchrl_grpo.training.transfer import evaluate_on_tensor, paired_gap

__all__ = [
    "CheckpointHook",
    "EvaluationHook",
    "GroupPlotHook",
    "Hook",
    "TrainerView",
    "default_hooks",
]

log = logging.getLogger(__name__)


class TrainerView(Protocol):
    """What hooks read and call of the trainer (a protocol: hooks do not import it).

    Example:
        >>> from torchrl_grpo.training import Trainer
        >>> names = ("save", "state_dict", "wall_seconds")
        >>> all(callable(getattr(Trainer, name)) for name in names)
        True
    """

    cfg: DictConfig
    run_dir: Path
    algo: Any
    policy: Any
    eval_policy: Any
    eval_env: EnvBase
    seed: int
    logger: Logger | None
    progress: Progress
    stop_requested: bool

    def state_dict(self, collector: Any = None) -> dict[str, Any]:
        """Everything needed to continue exactly: a checkpoint's dict."""

    def save(self, collector: Any = None, name: str = "last.pt") -> Path:
        """Write a checkpoint of the run (and of ``collector``) into the run folder."""

    def wall_seconds(self) -> float:
        """Seconds of training so far, the iteration in progress included."""


class Hook:
    """A side job of the training loop; every method does nothing by default.

    Attributes:
        phase: the name of its time metric (``time/<phase>``).

    Example:
        >>> class CountIterations(Hook):
        ...     phase = "count"
        ...     def __init__(self):
        ...         self.calls = 0
        ...     def due(self, trainer, batch):
        ...         return True
        ...     def on_iteration(self, trainer, batch, result):
        ...         self.calls += 1
        ...         return {"count/calls": float(self.calls)}
        >>> CountIterations().on_iteration(None, None, None)
        {'count/calls': 1.0}
    """

    phase = "hook"

    def due(self, trainer: TrainerView, batch: TensorDictBase) -> bool:
        """Whether :meth:`on_iteration` runs after this iteration's update."""
        return False

    def on_iteration(
        self, trainer: TrainerView, batch: TensorDictBase, result: Any
    ) -> dict[str, Any]:
        """The job of an iteration; metrics to log in the iteration's row (scalars, videos)."""
        return {}

    def on_train_start(self, trainer: TrainerView, result: Any) -> None:
        """Before the first batch is collected (and before the collector is built)."""

    def on_loop_end(self, trainer: TrainerView, result: Any) -> None:
        """The loop has ended (budget or Ctrl-C); the collector still runs."""

    def on_train_end(self, trainer: TrainerView, result: Any) -> None:
        """Training is done, not interrupted; the collector is shut down."""


def _parallel(cfg: DictConfig) -> dict[str, Any]:
    # Forked workers give the serial numbers, episode for episode (training/eval_episodes.py).
    exp = cfg.experiment
    return {
        "workers": eval_workers(exp.get("eval_workers")),
        "progress": sys.stderr.isatty(),
    }


def _every(trainer: TrainerView, every: int) -> bool:
    return every > 0 and trainer.progress.iteration % every == 0


class GroupPlotHook(Hook):
    """At the first iteration and each evaluation's (``experiment.eval_every``), plot a group.

    The group with the widest spread of returns goes to ``<run>/plots/`` and, as a
    video, to the logger (``collect/branch_group``, in the iteration's row). Only
    batches of branch groups are plotted, and only with a logger (not ``logger=none``).

    Example:
        >>> GroupPlotHook().phase
        'plot'
    """

    phase = "plot"

    def due(self, trainer: TrainerView, batch: TensorDictBase) -> bool:  # noqa: D102
        if str(trainer.cfg.logger.backend) == "none":
            return False  # nothing logged, nothing drawn (the tests' runs)
        every = int(trainer.cfg.experiment.eval_every)
        first = trainer.progress.iteration == 1
        return BRANCH_RETURN in batch.keys() and (first or _every(trainer, every))

    def on_iteration(  # noqa: D102
        self, trainer: TrainerView, batch: TensorDictBase, result: Any
    ) -> dict[str, Any]:
        returns = batch.get(BRANCH_RETURN)[:, :, 0, 0]
        group = int(returns.std(1).argmax())
        iteration = trainer.progress.iteration
        path = trainer.run_dir / "plots" / f"group_it{iteration:05d}.png"
        fig = plot_group(batch, group, path=path)
        return {"collect/branch_group": fig.video}  # a video, in the iteration's row


class CheckpointHook(Hook):
    """Every ``experiment.checkpoint_every`` iterations, on Ctrl-C and at the end: ``last.pt``.

    The end's checkpoint is written again after the final evaluation, with its row in
    the evaluation history (``scripts/evaluate.py`` draws the learning curve from it);
    everything else, random states included, stays as the loop left it, so that a
    resume with a bigger budget continues exactly.

    Example:
        >>> hook = CheckpointHook()
        >>> hook.phase
        'checkpoint'
    """

    phase = "checkpoint"

    def __init__(self) -> None:
        self._last: dict[str, Any] | None = None

    def due(self, trainer: TrainerView, batch: TensorDictBase) -> bool:  # noqa: D102
        return _every(trainer, int(trainer.cfg.experiment.checkpoint_every)) or (
            trainer.stop_requested
        )

    def on_iteration(  # noqa: D102
        self, trainer: TrainerView, batch: TensorDictBase, result: Any
    ) -> dict[str, float]:
        result.checkpoint = trainer.save()
        return {}

    def on_loop_end(self, trainer: TrainerView, result: Any) -> None:  # noqa: D102
        self._last = trainer.state_dict()
        result.checkpoint = save_checkpoint(self._last, trainer.run_dir / "last.pt")

    def on_train_end(self, trainer: TrainerView, result: Any) -> None:  # noqa: D102
        if self._last is not None:
            self._last.update(trainer.progress.state_dict())
            result.checkpoint = save_checkpoint(self._last, trainer.run_dir / "last.pt")


class EvaluationHook(Hook):
    """Deterministic evaluations during training, and the final one beside the baselines.

    Every ``experiment.eval_every`` iterations, and before the first batch of a run that
    starts from frame 0: ``eval_episodes`` episodes from
    ``eval_seed`` (``eval/`` metrics, a row of ``eval_history.jsonl`` that names its
    first seed and holds the algorithm's :meth:`~torchrl_grpo.training.Algorithm.counters`).
    At the end:
    ``final_eval_episodes`` episodes from ``final_eval_seed`` (a disjoint seed set) of
    the policy and of every baseline of ``experiment.baselines``, the baselines from
    their cache (:func:`~torchrl_grpo.training.evaluate_baselines`; ``results.md``,
    ``results.json``), the first episode as a GIF (with a ``logger`` other than ``none``), and the
    learning curve (:func:`~torchrl_grpo.training.run_plots.plot_run_curve`: the evaluation
    history, the final evaluation as a star, the baselines on the periodic seeds as
    lines, cached like the final ones). Where the tensor simulator covers the env,
    each evaluation also logs the paired transfer gap (``eval/transfer_*`` metrics).

    Example:
        >>> hook = EvaluationHook()
        >>> hook.phase
        'eval'
    """

    phase = "eval"

    def __init__(self) -> None:
        self._render: EnvBase | None = None
        self._final_baselines: list[EvalResult] = []

    def due(self, trainer: TrainerView, batch: TensorDictBase) -> bool:  # noqa: D102
        exp = trainer.cfg.experiment
        return _every(trainer, int(exp.eval_every)) and exp.eval_episodes > 0

    def on_iteration(  # noqa: D102
        self, trainer: TrainerView, batch: TensorDictBase, result: Any
    ) -> dict[str, float]:
        exp = trainer.cfg.experiment
        return self.evaluate(trainer, int(exp.eval_episodes), int(exp.eval_seed))[0]

    def on_train_start(self, trainer: TrainerView, result: Any) -> None:  # noqa: D102
        exp = trainer.cfg.experiment
        if trainer.progress.frames > 0 or int(exp.eval_every) <= 0 or exp.eval_episodes <= 0:
            return
        # The random streams are put back: with or without this evaluation, the run
        # trains the same weights.
        rng = get_rng_state()
        try:
            metrics = self.evaluate(trainer, int(exp.eval_episodes), int(exp.eval_seed))[0]
        finally:
            set_rng_state(rng)
        log_metrics(trainer.logger, metrics, step=0)

    def evaluate(
        self, trainer: TrainerView, episodes: int, seed: int, record: bool = False
    ) -> tuple[dict[str, float], EvalResult, Any]:
        """Evaluate the policy from ``seed``, add a history row; metrics, results, video.

        Where the tensor simulator covers the env, the same starting worlds are driven
        there too, and the paired transfer gap joins the metrics
        (:mod:`~torchrl_grpo.training.transfer`).
        """
        cfg = trainer.cfg
        if record and self._render is None:
            self._render = make_env(cfg.env, render_mode="rgb_array")
        # The evaluation envs are CPU envs: a run on a GPU evaluates a CPU copy.
        policy = trainer.eval_policy
        if any(p.device.type != "cpu" for p in policy.parameters()):
            policy = copy.deepcopy(policy).cpu()
        res, video = evaluate(
            trainer.eval_env,
            policy,
            episodes=episodes,
            seed=seed,
            max_steps=int(cfg.env.max_episode_steps),
            name=str(cfg.algo.name),
            record=self._render if record else None,
            **_parallel(cfg),
        )
        summary = res.summary()
        if tensor_covers(cfg.env):
            tensor = evaluate_on_tensor(cfg.env, policy, episodes=episodes, seed=seed)
            summary |= {f"transfer_{k}": v for k, v in paired_gap(res, tensor).items()}
        progress = trainer.progress
        # The seed names the seed set, so that a row is compared with baselines on its own.
        row = {"iteration": progress.iteration, "frames": progress.frames, "seed": seed}
        row |= trainer.algo.counters()  # a search's branch steps, counted beside the frames
        progress.eval_history.append({**row, "wall_seconds": trainer.wall_seconds(), **summary})
        with open(trainer.run_dir / "eval_history.jsonl", "a") as f:
            f.write(json.dumps(progress.eval_history[-1]) + "\n")
        metrics = {f"eval/{k}": v for k, v in summary.items() if k != "episodes"}
        return metrics, res, video

    def on_train_end(self, trainer: TrainerView, result: Any) -> None:  # noqa: D102
        cfg, exp = trainer.cfg, trainer.cfg.experiment
        episodes = int(exp.final_eval_episodes)
        frames = trainer.progress.frames
        video = None
        if episodes > 0:
            seed = int(exp.final_eval_seed)
            metrics, trained, video = self.evaluate(
                trainer, episodes, seed, records_video(cfg.logger)
            )
            trained.name = f"{cfg.algo.name} (trained)"
            final = {f"eval/final_{k[5:]}": v for k, v in metrics.items()}
            # One row: the final evaluation's metrics and its video.
            log_metrics(trainer.logger, {**final, "eval/final_episode": video}, step=frames)
            summary = trainer.progress.eval_history[-1]
            result.final = {k: v for k, v in summary.items() if k not in ("iteration", "seed")}
            cache = exp.get("baseline_cache")
            baselines = evaluate_baselines(
                cfg.env,
                list(exp.baselines),
                episodes=episodes,
                seed=seed,
                cache_dir=None if cache is None else Path(str(cache)),
                policy_seed=trainer.seed,
                **_parallel(cfg),
            )
            self._final_baselines = baselines
            results = [trained, *baselines]
            table = format_table(results)
            verdicts = paired_verdicts(trained, baselines)
            result.results_table = trainer.run_dir / "results.md"
            result.results_table.write_text(
                f"{cfg.env.scenario}, {episodes} episodes from seed {seed}, "
                f"after {frames} env frames\n\n{table}\n\n{verdicts}\n"
            )
            result.results_json = trainer.run_dir / "results.json"
            payload = {"frames": frames, "results": [r.to_dict() for r in results]}
            result.results_json.write_text(json.dumps(payload, indent=1))
            log.info("final evaluation:\n%s\n%s", table, verdicts)
        if video is not None:
            result.video = save_gif(video, trainer.run_dir / "eval_episode.gif")
        if trainer.progress.eval_history:
            result.curve = self._curve(trainer)

    def _curve(self, trainer: TrainerView) -> Path:
        # The baselines on the periodic seed set, cached: lines comparable with the curve.
        cfg, exp = trainer.cfg, trainer.cfg.experiment
        history = trainer.progress.eval_history
        baselines = []
        if any(r.get("seed") == int(exp.eval_seed) for r in history) and exp.eval_episodes > 0:
            cache = exp.get("baseline_cache")
            baselines = evaluate_baselines(
                cfg.env,
                list(exp.baselines),
                episodes=int(exp.eval_episodes),
                seed=int(exp.eval_seed),
                cache_dir=None if cache is None else Path(str(cache)),
                policy_seed=trainer.seed,
                **_parallel(cfg),
            )
        return plot_run_curve(
            history,
            trainer.run_dir / "learning_curve.png",
            label=str(cfg.algo.name),
            final_seed=int(exp.final_eval_seed),
            baselines=baselines,
            final=self._final_baselines,
            title=f"{cfg.env.scenario}: deterministic evaluation",
        )


def default_hooks() -> list[Hook]:
    """The trainer's hooks, in the order they run: plots, evaluation, checkpoints.

    Example:
        >>> [type(hook).__name__ for hook in default_hooks()]
        ['GroupPlotHook', 'EvaluationHook', 'CheckpointHook']
    """
    return [GroupPlotHook(), EvaluationHook(), CheckpointHook()]
