"""``algo=grpo_lab``: GRPO with every research setting as a config key.

The recommended GRPO recipes fix most of GRPO's settings
(:data:`~torchrl_grpo.training.algos.grpo_config.FIXED_SETTINGS`); the lab's schemas
make each of them a key again, with the defaults the schemas had before they were
fixed, so that the commands of ``docs/lab/`` run with ``algo=grpo_lab`` (and
``model=lab`` for ensembles and priors). A checkpoint of a GRPO run that used other
values than the recipe's reads as a ``grpo_lab`` run
(:func:`~torchrl_grpo.training.config.typed_config`).

Example:
    >>> import torchrl_grpo.experimental  # registers algo=grpo_lab
    >>> from torchrl_grpo.training import compose_config
    >>> cfg = compose_config(["experiment=smoke", "algo=grpo_lab", "algo.roots=continue"])
    >>> print(cfg.algo.name, cfg.algo.roots, cfg.algo.first_action)
    grpo_lab continue enumerate
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from omegaconf import MISSING, DictConfig, OmegaConf
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.experimental.crash_head_tail import (
    BASE_TAIL_CRASHED,
    base_tail_crashes,
    check_crash_head_tail,
)
from torchrl_grpo.experimental.group_distill import GroupFitLossName, GroupFitWeightingName
from torchrl_grpo.experimental.lagging_tail import check_tail_sync, lagging_copy
from torchrl_grpo.experimental.neighbour_features import NeighboursKind
from torchrl_grpo.experimental.prior import PriorName, check_prior
from torchrl_grpo.experimental.trunk_clock import (
    TrunkPolicyName,
    check_trunk_bounds,
    trunk_exploration,
    trunk_schedule,
)
from torchrl_grpo.training.algos.enumerated import ActionWeightsName
from torchrl_grpo.training.algos.grpo import GRPO
from torchrl_grpo.training.algos.grpo_config import GRPOConfig
from torchrl_grpo.training.algos.registry import register_algorithm
from torchrl_grpo.training.choices import (
    AggregationName,
    BaselineName,
    BootstrapName,
    CrashLabelName,
    FirstActionName,
    KLEstimatorName,
    ReturnsName,
    RootKindName,
    ScaleRewards,
    SelectionName,
    choice_enum,
)
from torchrl_grpo.training.group_schemas import GroupRolloutConfig, ModelConfig
from torchrl_grpo.training.metrics import PhaseTimer
from torchrl_grpo.training.model_builder import ModelArchitecture

__all__ = ["GRPOLab", "GRPOLabConfig", "GRPOLabModelConfig", "GRPOLabRolloutConfig"]

GRPOLabName = choice_enum(
    "GRPOLabName", Literal["grpo_lab"], "The experimental GRPO.", module=__name__
)
#: ``model=lab``'s ``model.kind``: the core's networks and the lab's (``neighbours``).
LabModelKind = choice_enum(
    "LabModelKind",
    Literal[ModelArchitecture, NeighboursKind],
    "Network over the Kinematics table, the lab's kinds included.",
    module=__name__,
)


@dataclass
class GRPOLabConfig(GRPOConfig):
    """``algo=grpo_lab``: GRPOConfig plus every setting the recipes fix.

    ``crash_label`` says what the crash head learns of a branch the horizon cut alive: 0
    (``branch``), or its own crash estimate there (``bootstrap``). ``bootstrap=survival``
    builds that estimate for the horizon bootstrap, and then it labels those rows too
    whatever ``crash_label`` says (``experiment=best``'s teachers were trained so):
    ``crash_label=branch`` keeps 0/1 labels only with the other bootstraps.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.structured(GRPOLabConfig(name="grpo_lab"))
        >>> print(cfg.roots, cfg.first_action, cfg.group_fit_loss)
        trunk sample cross_entropy
    """

    name: GRPOLabName = MISSING
    roots: RootKindName = RootKindName["trunk"]
    select: SelectionName = SelectionName["best"]
    returns: ReturnsName = ReturnsName["branch"]
    bootstrap: BootstrapName = BootstrapName["batch_mean"]
    crash_penalty: float = 0.0
    baseline: BaselineName = BaselineName["mean"]
    scale_rewards: ScaleRewards = ScaleRewards["group"]
    gamma: float = 1.0
    dual_clip: float | None = None
    kl_estimator: KLEstimatorName = KLEstimatorName["k3"]
    aggregation: AggregationName = AggregationName["dapo"]
    ref_model_sync_steps: int | None = 64
    ref_model_mixup_alpha: float = 1.0
    explore_steps: int | None = None
    first_action: FirstActionName = FirstActionName["sample"]
    action_weights: ActionWeightsName = ActionWeightsName["uniform"]
    tail_sync_batches: int | None = None
    trunk: TrunkPolicyName = TrunkPolicyName["sample"]
    group_fit_temperature: float = 0.1
    group_fit_weighting: GroupFitWeightingName = GroupFitWeightingName["uniform"]
    group_fit_coeff: float = 0.0
    group_fit_loss: GroupFitLossName = GroupFitLossName["cross_entropy"]
    crash_head_coeff: float = 1.0
    crash_label: CrashLabelName = CrashLabelName["branch"]
    crash_head_tail: bool = False
    max_minibatches: int | None = None


@dataclass
class GRPOLabRolloutConfig(GroupRolloutConfig):
    """``rollout`` of ``algo=grpo_lab``: how trunks run, as keys."""

    live_trunks: bool = False
    stagger_trunks: bool = False
    full_horizon_roots: bool = False
    first_root_step: int = 0


@dataclass
class GRPOLabModelConfig(ModelConfig):
    """``model=lab``: any kind's sizes (the lab's ``neighbours`` too), a prior, an ensemble."""

    kind: LabModelKind = LabModelKind["mlp"]
    num_cells: list[int] = field(default_factory=lambda: [256, 256])
    embed_dim: int = 64
    num_heads: int = 2
    encoder_cells: list[int] = field(default_factory=lambda: [64])
    decoder_cells: list[int] = field(default_factory=lambda: [64, 64])
    prior: PriorName | None = None
    prior_weight: float = 2.0
    ensemble: int = 1
    bagging: bool = False


@register_algorithm
class GRPOLab(GRPO):
    """GRPO whose settings are all keys (``algo=grpo_lab``); nothing is fixed.

    Example:
        >>> from torchrl_grpo.training.algos.registry import algorithm_for
        >>> algorithm_for({"name": "grpo_lab"}) is GRPOLab, GRPOLab.fixed_settings("grpo_lab")
        (True, {})
    """

    names = ("grpo_lab",)
    config_class = GRPOLabConfig
    config_name = "base_grpo_lab"
    rollout_config_class = GRPOLabRolloutConfig

    def __init__(self, cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase) -> None:
        super().__init__(cfg, policy, env)
        check_crash_head_tail(self.cfg.algo, self.crash_head is not None, int(env.action_spec.n))

    @classmethod
    def fixed_settings(cls, name: str) -> dict[str, dict[str, Any]]:
        """None: the lab's schemas have every setting."""
        return {}

    @classmethod
    def check_config(cls, cfg: DictConfig) -> None:
        """The lagging tail's checks, GRPO's, the trunks' bounds', and the prior's."""
        check_tail_sync(cfg.algo)
        super().check_config(cfg)
        check_trunk_bounds(cfg.algo, cfg.get("rollout"))
        if "model" in cfg and not OmegaConf.is_missing(cfg, "model"):
            check_prior(cfg.model)
            check_crash_head_tail(cfg.algo, bool(cfg.model.get("crash_head", False)), None)

    @classmethod
    def make_tail_policy(
        cls, algo_cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase
    ) -> nn.Module | None:
        """GRPO's, or with ``algo.tail_sync_batches`` a lagging copy of the policy."""
        if str(algo_cfg.tail_policy) == "learner" and algo_cfg.tail_sync_batches is not None:
            return lagging_copy(policy)
        return super().make_tail_policy(algo_cfg, policy, env)

    @classmethod
    def trunk_schedule(cls, rollout: DictConfig, step_limit: int) -> tuple[int, int, int | None]:
        """The trunks' schedule with ``rollout.first_root_step`` and ``full_horizon_roots``."""
        return trunk_schedule(rollout, step_limit)

    @classmethod
    def trunk_exploration(cls, algo_cfg: DictConfig) -> ExplorationType:
        """How the policy acts on trunks: ``algo.trunk``."""
        return trunk_exploration(algo_cfg)

    @classmethod
    def learner_branches(cls, algo_cfg: DictConfig) -> int | None:
        """GRPO's, or with ``algo.crash_head_tail`` the first half of each group."""
        if algo_cfg.get("crash_head_tail", False):
            return int(algo_cfg.group_size) // 2
        return super().learner_branches(algo_cfg)

    @classmethod
    def trained_branches(cls, algo_cfg: DictConfig) -> int:
        """GRPO's, or with ``algo.crash_head_tail`` the learner's half of each group."""
        return cls.learner_branches(algo_cfg) or super().trained_branches(algo_cfg)

    def batch_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        """GRPO's, or with ``algo.crash_head_tail`` of the learner's half of each group."""
        half = self.learner_branches(self.cfg.algo)
        return super().batch_metrics(batch if half is None else batch[:, :half])

    def update(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """GRPO's update; with ``algo.crash_head_tail``, of the learner's half of each group."""
        if not self.cfg.algo.crash_head_tail:
            return super().update(batch, timer)
        learner, labels = base_tail_crashes(batch)
        return super().update(learner.set(BASE_TAIL_CRASHED, labels), timer)

    def crash_targets(self, batch: TensorDictBase) -> torch.Tensor:
        """GRPO's labels, or with ``algo.crash_head_tail`` the base tail's crashes."""
        if self.cfg.algo.crash_head_tail:
            return batch.get(BASE_TAIL_CRASHED)
        return super().crash_targets(batch)

    def after_batch(self, iteration: int) -> None:
        """Copy the policy into the lagging tail policy every ``algo.tail_sync_batches``."""
        super().after_batch(iteration)
        sync = self.cfg.algo.tail_sync_batches
        if self.tail_policy is not None and sync is not None and iteration % int(sync) == 0:
            self.tail_policy.load_state_dict(self.policy.state_dict())

    @classmethod
    def model_schema(cls, kind: str) -> type[ModelConfig]:
        """``model=lab``'s schema, whatever the kind."""
        return GRPOLabModelConfig

    @classmethod
    def extra_schemas(cls) -> dict[str, type]:
        """The lab's ``rollout`` and ``model`` schemas."""
        return {"rollout": GRPOLabRolloutConfig, "model": GRPOLabModelConfig}
