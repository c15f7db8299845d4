"""What the distillations share: label the student's own states, keep them, fit all kept ones.

The student drives (TorchRL's ``Collector``, as PPO's trunks); a subclass labels every
state it visits (with teachers' logits: ``algo=distill``; with the search over a run:
``algo=search_distill``) and hands the labels to :meth:`LabelledFit.fit_kept`. The
labelled states are kept, up to ``algo.replay_frames`` of them, and each batch trains
``algo.max_minibatches`` minibatches drawn from all of them: DAgger. With
``algo.refit_steps``, the run ends with a second fit over everything kept
(:meth:`LabelledFit.finish`).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.training.algos.base import AlgoConfig
from torchrl_grpo.training.algos.episodes import TrunkEpisodes
from torchrl_grpo.training.algos.labelled import LabelledStates
from torchrl_grpo.training.metrics import PhaseTimer

__all__ = ["LabelledFit", "LabelledFitConfig", "cosine_lr"]

log = logging.getLogger(__name__)

#: Minibatches of the final fit between two learning-rate updates and stop checks.
REFIT_CHUNK = 250
#: The final fit's first rate: a fine-tuning rate, as the lab's second fits had
#: (docs/lab/targets.md, "A finer fit").
REFIT_LR = 3e-4


@dataclass
class LabelledFitConfig(AlgoConfig):
    """The keys of a distillation: its teachers, and the states it keeps.

    ``teachers`` are checkpoints of runs on the same scenario and env config;
    ``teacher_runs`` are runs to train first, each its overrides in one string
    (:mod:`~torchrl_grpo.training.teacher_runs`), ``teacher_processes`` at a time;
    ``replay_frames`` is how many labelled states are kept (the oldest go first);
    ``max_minibatches`` of ``minibatch_size`` states are drawn from them per batch
    (``null``: ``epochs`` passes over all of them, a cost that grows with what is kept);
    ``crash_head_coeff`` weighs the fit of a crash head (with ``model.crash_head``);
    ``refit_steps`` minibatches of a final fit over all kept states follow the last
    batch, from the run's weights with Adam restarted at :data:`REFIT_LR` on a cosine
    to 0 (``0``: none).

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.structured(LabelledFitConfig(name="distill"))
        >>> cfg.replay_frames, cfg.epochs, cfg.entropy_coeff, cfg.refit_steps
        (1000000, 1, 0.0, 0)
    """

    teachers: list[str] = field(default_factory=list)
    teacher_runs: list[str] = field(default_factory=list)
    teacher_processes: int = 1
    replay_frames: int = 1_000_000
    entropy_coeff: float = 0.0
    epochs: int = 1
    max_minibatches: int | None = 200
    crash_head_coeff: float = 1.0
    refit_steps: int = 0


def cosine_lr(lr: float, done: int, total: int) -> float:
    """The rate after ``done`` of ``total`` steps on a cosine from ``lr`` to 0.

    Example:
        >>> cosine_lr(1.0, 0, 10), cosine_lr(1.0, 5, 10), round(cosine_lr(1.0, 10, 10), 12)
        (1.0, 0.5, 0.0)
    """
    return 0.5 * lr * (1.0 + math.cos(math.pi * min(done, total) / total))


class LabelledFit(TrunkEpisodes):
    """A :class:`TrunkEpisodes` algorithm that fits the labelled states it keeps.

    Example:
        >>> from torchrl_grpo.training import TeacherDistill
        >>> issubclass(TeacherDistill, LabelledFit)
        True
    """

    def __init__(self, cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase) -> None:
        super().__init__(cfg, policy, env)
        self.replay = LabelledStates(int(cfg.algo.replay_frames))
        #: Whether the final fit (``algo.refit_steps``) is done: a resumed run skips it.
        self.refitted = False

    @classmethod
    def check_config(cls, cfg: DictConfig) -> None:
        """Also refuses teacher_processes < 1, a replay under a minibatch, a bad refit."""
        super().check_config(cfg)
        algo = cfg.algo
        if algo.teacher_processes < 1:
            raise ValueError(
                f"algo.teacher_processes must be at least 1 (got {algo.teacher_processes})"
            )
        if algo.replay_frames < algo.minibatch_size:
            raise ValueError(
                f"algo.replay_frames ({algo.replay_frames}) must hold at least one "
                f"minibatch (algo.minibatch_size={algo.minibatch_size})"
            )
        if algo.refit_steps < 0:
            raise ValueError(f"algo.refit_steps must be >= 0 (got {algo.refit_steps})")
        if algo.refit_steps > 0 and cfg.optim.get("ema_decay") is not None:
            # The saved policy would be the average, which the final fit never moves.
            raise ValueError(
                "algo.refit_steps fits the live weights at the end of the run: "
                f"set optim.ema_decay=null (got {cfg.optim.ema_decay})"
            )

    def _draw(self, minibatches: int) -> TensorDictBase:
        # Drawn with replacement: a fixed cost, however many states are kept.
        kept = len(self.replay)
        draws = int(self.cfg.algo.minibatch_size) * minibatches
        return self.replay.rows[torch.randint(kept, (min(draws, kept),))]

    def fit_kept(self, labels: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """Keep ``labels`` (a flat batch of labelled states), then train on all kept."""
        self.replay.extend(labels)
        kept = len(self.replay)
        algo = self.cfg.algo
        rows = self.replay.rows
        if algo.max_minibatches is not None:
            rows = self._draw(int(algo.max_minibatches))
        with timer("update"):
            stats = self.optimise(rows)
        stats["train/replay_steps"] = float(kept)
        return stats

    def finish(self, timer: PhaseTimer, stop: Callable[[], bool]) -> dict[str, float]:
        """The final fit: ``algo.refit_steps`` minibatches drawn from every kept state.

        A fit that adds states as it goes ends on its newest ones at a rate annealed
        for them; this one starts from its weights with a fresh Adam at
        :data:`REFIT_LR`, on a cosine to 0, over all of them alike. Stopped (``stop()``
        true between chunks), it puts the weights and the optimiser back as they were,
        so that the checkpoint is the run's end and a resume fits again from there.
        """
        algo = self.cfg.algo
        steps = int(algo.refit_steps)
        if steps == 0 or self.refitted or len(self.replay) == 0:
            return {}
        before = copy.deepcopy((self.loss.state_dict(), self.optimizer.state_dict()))
        self.optimizer.state.clear()  # Adam's moments start again, as for a new fit
        log.info("final fit: %d minibatches over %d kept states", steps, len(self.replay))
        stats: dict[str, float] = {}
        done = 0
        with timer("refit"):
            while done < steps:
                if stop():
                    self.loss.load_state_dict(before[0])
                    self.optimizer.load_state_dict(before[1])
                    log.warning("final fit stopped at %d of %d minibatches: undone", done, steps)
                    return {}
                chunk = min(REFIT_CHUNK, steps - done)
                # The rate of the chunk's middle step: a cosine in steps of REFIT_CHUNK.
                for group in self.optimizer.param_groups:
                    group["lr"] = cosine_lr(REFIT_LR, done + chunk // 2, steps)
                stats = self.optimise(self._draw(chunk), limit=chunk)
                done += chunk
                if done % (10 * REFIT_CHUNK) == 0 or done == steps:
                    log.info(
                        "final fit: %d of %d minibatches, loss %.4f",
                        done,
                        steps,
                        stats.get("train/loss_total", float("nan")),
                    )
        self.refitted = True
        return {f"refit/{key.split('/', 1)[-1]}": value for key, value in stats.items()}

    def state_dict(self) -> dict[str, Any]:  # noqa: D102
        return {
            **super().state_dict(),
            "replay": self.replay.state_dict(),
            "refitted": self.refitted,
        }

    def load_state_dict(self, checkpoint: dict[str, Any], source: str = "") -> None:  # noqa: D102
        super().load_state_dict(checkpoint, source)
        self.replay.load_state_dict(checkpoint["replay"])
        self.refitted = bool(checkpoint.get("refitted", False))
