"""PPO, the baseline: TorchRL's ``Collector``, GAE over a value network and ``ClipPPOLoss``.

Each batch is ``rollout.frames_per_batch`` steps of the workers' episodes, ``[W, T]``.
The advantage is recomputed with the updated critic before every epoch, as TorchRL's
``sota-implementations`` do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import torch
from omegaconf import MISSING, DictConfig
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from torchrl_grpo.training.algos.base import AlgoConfig
from torchrl_grpo.training.algos.episodes import TrunkEpisodes
from torchrl_grpo.training.algos.registry import register_algorithm
from torchrl_grpo.training.choices import choice_enum
from torchrl_grpo.training.metrics import PhaseTimer
from torchrl_grpo.training.model_builder import make_value

__all__ = ["PPO", "CriticLoss", "PPOConfig", "PPOVariant"]

#: PPO's name (``algo.name``).
PPOVariant = Literal["ppo"]
#: The value loss of ``ClipPPOLoss`` (``algo.loss_critic_type``).
CriticLoss = Literal["l1", "l2", "smooth_l1"]

PPOName = choice_enum("PPOName", PPOVariant, "The PPO variant.", module=__name__)
CriticLossName = choice_enum("CriticLossName", CriticLoss, "The value loss.", module=__name__)


@dataclass
class PPOConfig(AlgoConfig):
    """PPO baseline: TorchRL's ``ClipPPOLoss`` with a value network and GAE.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training import PPOConfig
        >>> cfg = OmegaConf.merge(OmegaConf.structured(PPOConfig), {"name": "ppo", "gamma": 0.99})
        >>> cfg.gamma, cfg.lmbda, cfg.clip_epsilon, str(cfg.loss_critic_type)
        (0.99, 0.95, 0.2, 'smooth_l1')
    """

    name: PPOName = MISSING
    gamma: float = 0.9
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    critic_coeff: float = 0.5
    normalize_advantage: bool = True
    loss_critic_type: CriticLossName = CriticLossName["smooth_l1"]


@register_algorithm
class PPO(TrunkEpisodes):
    """PPO with a critic of the policy's architecture, GAE recomputed every epoch.

    Example:
        >>> from torchrl_grpo.training import PPO, compose_config, make_env, make_policy
        >>> cfg = compose_config(["experiment=smoke", "algo=ppo"])
        >>> env = make_env(cfg.env, seed=0)
        >>> ppo = PPO(cfg, make_policy(cfg.model, env), env)
        >>> type(ppo.loss).__name__, type(ppo.advantage).__name__, ppo.value is not None
        ('ClipPPOLoss', 'GAE', True)
    """

    names = get_args(PPOVariant)
    config_class = PPOConfig
    config_name = "base_ppo"

    def __init__(self, cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase) -> None:
        super().__init__(cfg, policy, env)
        self.advantage = self.make_advantage(cfg.algo, self.value)

    @classmethod
    def make_value(cls, model_cfg: DictConfig, env: EnvBase) -> ValueOperator:
        """The critic: the policy's architecture with one output."""
        return make_value(model_cfg, env)

    @classmethod
    def make_loss(
        cls, algo_cfg: DictConfig, policy: ProbabilisticActor, value: ValueOperator | None = None
    ) -> ClipPPOLoss:
        """TorchRL's ``ClipPPOLoss`` over the policy and ``value``."""
        if value is None:
            raise ValueError("PPO needs a value network")
        return ClipPPOLoss(
            policy,
            value,
            clip_epsilon=float(algo_cfg.clip_epsilon),
            entropy_bonus=float(algo_cfg.entropy_coeff) > 0,
            entropy_coeff=float(algo_cfg.entropy_coeff),
            critic_coeff=float(algo_cfg.critic_coeff),
            loss_critic_type=str(algo_cfg.loss_critic_type),
            normalize_advantage=bool(algo_cfg.normalize_advantage),
        )

    @classmethod
    def make_advantage(cls, algo_cfg: DictConfig, value: ValueOperator | None = None) -> GAE:
        """GAE over ``value``."""
        if value is None:
            raise ValueError("GAE needs a value network")
        return GAE(
            gamma=float(algo_cfg.gamma),
            lmbda=float(algo_cfg.lmbda),
            value_network=value,
            average_gae=False,
        )

    def update(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """GAE, then epochs of minibatches (GAE recomputed before each)."""
        data = batch.exclude("state", ("next", "state"))
        with timer("advantage"), torch.no_grad():
            self.advantage(data)
        adv = data.get("advantage")
        stats = {
            "train/advantage_mean": float(adv.mean()),
            "train/advantage_std": float(adv.std()),
            "train/advantage_abs_mean": float(adv.abs().mean()),
            "train/value_mean": float(data.get("state_value").mean()),
            "train/value_target_mean": float(data.get("value_target").mean()),
        }

        def refresh() -> TensorDictBase:
            with torch.no_grad():
                self.advantage(data)
            return data.reshape(-1)

        with timer("update"):
            stats.update(self.optimise(data.reshape(-1), refresh=refresh))
        return stats
