"""What the distillations share: label the student's own states, keep them, fit all kept ones.

The student drives (TorchRL's ``Collector``, as PPO's trunks); a subclass labels every
state it visits (with teachers' logits: ``algo=distill``; with the search over a run:
``algo=search_distill``) and hands the labels to :meth:`LabelledFit.fit_kept`. The
labelled states are kept, up to ``algo.replay_frames`` of them, and each batch trains
``algo.max_minibatches`` minibatches drawn from all of them: DAgger.
"""

from __future__ import annotations

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

__all__ = ["LabelledFit", "LabelledFitConfig"]


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
    ``start_from_run`` starts the student from its first teacher's weights (``init_from``
    that run, once the teacher runs have trained): the same network refitted.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.structured(LabelledFitConfig(name="distill"))
        >>> cfg.replay_frames, cfg.epochs, cfg.entropy_coeff
        (1000000, 1, 0.0)
    """

    teachers: list[str] = field(default_factory=list)
    teacher_runs: list[str] = field(default_factory=list)
    teacher_processes: int = 1
    replay_frames: int = 1_000_000
    entropy_coeff: float = 0.0
    epochs: int = 1
    max_minibatches: int | None = 200
    crash_head_coeff: float = 1.0
    start_from_run: bool = False


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

    @classmethod
    def check_config(cls, cfg: DictConfig) -> None:
        """Also refuses teacher_processes < 1, a replay under a minibatch, and two starts."""
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
        first = [str(path) for path in algo.teachers[:1]]
        if algo.start_from_run and cfg.get("init_from") and str(cfg.init_from) not in first:
            raise ValueError(
                "algo.start_from_run=true starts the student from its first teacher's "
                f"weights: drop init_from={cfg.init_from}, or set algo.start_from_run=false"
            )

    @classmethod
    def with_fixed_settings(cls, cfg: DictConfig) -> DictConfig:
        """Also ``init_from`` the first teacher under ``algo.start_from_run`` (once it is known)."""
        cfg = super().with_fixed_settings(cfg)
        if cfg.algo.get("start_from_run") and cfg.algo.teachers and not cfg.get("init_from"):
            cfg.init_from = str(cfg.algo.teachers[0])
        return cfg

    def fit_kept(self, labels: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """Keep ``labels`` (a flat batch of labelled states), then train on all kept."""
        self.replay.extend(labels)
        kept = len(self.replay)
        algo = self.cfg.algo
        rows = self.replay.rows
        if algo.max_minibatches is not None:
            # Drawn with replacement: a fixed cost per batch, however many states are kept.
            draws = int(algo.minibatch_size) * int(algo.max_minibatches)
            rows = rows[torch.randint(kept, (min(draws, kept),))]
        with timer("update"):
            stats = self.optimise(rows)
        stats["train/replay_steps"] = float(kept)
        return stats

    def state_dict(self) -> dict[str, Any]:  # noqa: D102
        return {**super().state_dict(), "replay": self.replay.state_dict()}

    def load_state_dict(self, checkpoint: dict[str, Any], source: str = "") -> None:  # noqa: D102
        super().load_state_dict(checkpoint, source)
        self.replay.load_state_dict(checkpoint["replay"])
