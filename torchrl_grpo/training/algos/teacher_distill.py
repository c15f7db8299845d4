"""Teacher distillation (``algo=distill``): one policy trained on trained policies' labels.

The student drives (TorchRL's ``Collector``, as PPO's trunks), and every state it visits
is labelled with the teachers' mean logits
(:func:`~torchrl_grpo.training.teacher_loading.load_teachers`):
DAgger with soft labels. The labelled states are kept, up to ``algo.replay_frames`` of
them, and each batch trains ``algo.max_minibatches`` minibatches drawn from all of them
through :class:`~torchrl_grpo.objectives.TeacherDistillLoss`. A frame is a step of the
student's worlds, as for the other algorithms; the teachers' own frames are not counted
here, and a result should add them. With ``model.crash_head``, the student also fits
its teachers' crash heads (:class:`~torchrl_grpo.objectives.TeacherCrashLoss`, weighted
by ``algo.crash_head_coeff``); every teacher must then have one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from omegaconf import MISSING, DictConfig
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, ValueOperator

from torchrl_grpo.objectives.teacher_losses import TeacherCrashLoss, TeacherDistillLoss
from torchrl_grpo.training.algos.labelled_fit import LabelledFit, LabelledFitConfig
from torchrl_grpo.training.algos.registry import register_algorithm
from torchrl_grpo.training.choices import choice_enum
from torchrl_grpo.training.metrics import PhaseTimer
from torchrl_grpo.training.teacher_loading import load_teachers

__all__ = ["TEACHER_CRASH_LOGITS", "DistillConfig", "DistillVariant", "TeacherDistill"]

#: Where the teachers' mean crash logits are kept beside each state (``model.crash_head``).
TEACHER_CRASH_LOGITS = "teacher_crash_logits"

#: Teacher distillation's name (``algo.name``).
DistillVariant = Literal["distill"]

DistillName = choice_enum("DistillName", DistillVariant, "The distillation.", module=__name__)


@dataclass
class DistillConfig(LabelledFitConfig):
    """``algo=distill``: the student fits the teachers' mean logits on its own states.

    The keys of :class:`~torchrl_grpo.training.algos.labelled_fit.LabelledFitConfig`;
    ``crash_head_coeff`` weighs the fit of the teachers' crash heads.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.merge(OmegaConf.structured(DistillConfig),
        ...                       {"name": "distill", "teachers": ["runs/a/last.pt"]})
        >>> cfg.replay_frames, cfg.minibatch_size, cfg.max_minibatches
        (1000000, 1024, 200)
    """

    name: DistillName = MISSING
    minibatch_size: int = 1024


@register_algorithm
class TeacherDistill(LabelledFit):
    """DAgger with the teachers' soft labels, on the student's own trunks.

    Example:
        >>> from torchrl_grpo.training import compose_config
        >>> cfg = compose_config(["algo=distill"])  # no teachers given
        >>> try:
        ...     TeacherDistill.check_config(cfg)
        ... except ValueError as err:
        ...     print(str(err)[:39])
        algo=distill needs algo.teachers: the c
    """

    names = get_args(DistillVariant)
    config_class = DistillConfig
    config_name = "base_distill"
    trains_crash_head = True

    def __init__(self, cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase) -> None:
        super().__init__(cfg, policy, env)
        head = self.trained_head
        self.crash_head = (
            None if head is None else TeacherCrashLoss(head, coeff=float(cfg.algo.crash_head_coeff))
        )
        crash_key = None if head is None else TEACHER_CRASH_LOGITS
        self.teachers = load_teachers(
            list(cfg.algo.teachers), cfg.env, env, crash_key=crash_key
        ).to(cfg.device)

    @classmethod
    def check_config(cls, cfg: DictConfig) -> None:
        """Also refuses no teachers."""
        super().check_config(cfg)
        algo = cfg.algo
        if not algo.teachers and not algo.get("teacher_runs"):
            raise ValueError(
                "algo=distill needs algo.teachers: the checkpoints whose policies it "
                "distils, e.g. algo.teachers=[runs/a/last.pt,runs/b/last.pt] (or "
                "algo.teacher_runs, runs to train first: experiment=best)"
            )

    @classmethod
    def make_loss(
        cls, algo_cfg: DictConfig, policy: ProbabilisticActor, value: ValueOperator | None = None
    ) -> TeacherDistillLoss:
        """The KL divergence from the teachers' mean logits to the policy."""
        return TeacherDistillLoss(policy)

    def loss_terms(self, minibatch: TensorDictBase) -> TensorDictBase:
        """The KL divergence to the teachers, and the crash heads' fit when on."""
        out = self.loss(minibatch)
        if self.crash_head is not None:
            out.update(self.crash_head(minibatch))
        return out

    def update(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """Label the batch's states, keep them, then train on minibatches of all kept."""
        with timer("teacher"):
            data = self.teachers(batch.reshape(-1).select(*self.policy.in_keys))
        return self.fit_kept(data, timer)
