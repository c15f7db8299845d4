"""Builders of the ``algo`` and ``optim`` groups: losses, advantages, reference, optimiser."""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss, LossModule
from torchrl.objectives.value import GAE

from torchrl_grpo.objectives import GroupRelativeAdvantage, GRPOLoss, ReferenceSync

__all__ = [
    "TRAIN_REWARD",
    "is_grpo",
    "make_advantage",
    "make_loss",
    "make_optimizer",
    "make_reference_sync",
]


#: The reward GRPO advantages are computed from: the env's reward plus, on the last step
#: of a branch cut by the horizon, the bootstrap of the episode steps left.
TRAIN_REWARD = ("next", "train_reward")


def is_grpo(algo_cfg: DictConfig) -> bool:
    """Whether the algorithm is one of the critic-free GRPO variants.

    Example:
        >>> from omegaconf import OmegaConf
        >>> is_grpo(OmegaConf.create({"name": "ppo"}))
        False
    """
    return str(algo_cfg.name) in ("grpo_branch", "grpo_episode")


def make_loss(
    algo_cfg: DictConfig, policy: ProbabilisticActor, value: ValueOperator | None = None
) -> LossModule:
    """``GRPOLoss`` for GRPO, TorchRL's ``ClipPPOLoss`` (with ``value``) for PPO.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.config import GRPOConfig, ModelConfig
        >>> from torchrl_grpo.training.model_builder import make_policy
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> policy = make_policy(OmegaConf.structured(ModelConfig), HighwayEnv(seed=0))
        >>> loss = make_loss(OmegaConf.structured(GRPOConfig(name="grpo_branch")), policy)
        >>> type(loss).__name__, loss.aggregation
        ('GRPOLoss', 'dapo')
    """
    if is_grpo(algo_cfg):
        kl = algo_cfg.kl_to_ref_coeff
        return GRPOLoss(
            policy,
            clip_epsilon=(float(algo_cfg.clip_epsilon_low), float(algo_cfg.clip_epsilon_high)),
            dual_clip=algo_cfg.dual_clip,
            kl_to_ref_coeff=None if kl is None else float(kl),
            kl_estimator=str(algo_cfg.kl_estimator),
            entropy_bonus=float(algo_cfg.entropy_coeff) > 0,
            entropy_coeff=float(algo_cfg.entropy_coeff),
            aggregation=str(algo_cfg.aggregation),
        )
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


def make_advantage(
    algo_cfg: DictConfig, value: ValueOperator | None = None
) -> TensorDictModuleBase:
    """Group-relative advantage (GRPO) or GAE over the value network (PPO).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.config import GRPOConfig
        >>> adv = make_advantage(OmegaConf.structured(GRPOConfig(name="grpo_branch")))
        >>> adv.returns, adv.in_keys[2]
        ('branch', ('next', 'train_reward'))
    """
    if is_grpo(algo_cfg):
        # The trainer writes the training reward (with the horizon bootstrap) beside the
        # env's reward, which stays untouched for the metrics.
        return GroupRelativeAdvantage(
            returns=str(algo_cfg.returns),
            baseline=str(algo_cfg.baseline),
            scale_rewards=str(algo_cfg.scale_rewards),
            gamma=float(algo_cfg.gamma),
        ).set_keys(reward=TRAIN_REWARD)
    if value is None:
        raise ValueError("GAE needs a value network")
    return GAE(
        gamma=float(algo_cfg.gamma),
        lmbda=float(algo_cfg.lmbda),
        value_network=value,
        average_gae=False,
    )


def make_reference_sync(algo_cfg: DictConfig, loss: LossModule) -> ReferenceSync | None:
    """The reference-policy updater of a GRPO loss with a KL term (``None`` otherwise).

    ``algo.ref_model_sync_steps=null`` keeps the reference frozen at the initial policy
    (``None``): with ``model.prior``, the KL then holds the learner to the base policy.

    Example:
        >>> from omegaconf import OmegaConf
        >>> make_reference_sync(OmegaConf.create({"name": "ppo"}), None) is None
        True
    """
    if (
        not is_grpo(algo_cfg)
        or algo_cfg.kl_to_ref_coeff is None
        or algo_cfg.ref_model_sync_steps is None
    ):
        return None
    return ReferenceSync(
        loss,
        ref_model_sync_steps=int(algo_cfg.ref_model_sync_steps),
        ref_model_mixup_alpha=float(algo_cfg.ref_model_mixup_alpha),
    )


def make_optimizer(optim_cfg: DictConfig, loss: LossModule) -> torch.optim.Optimizer:
    """Adam over the loss's trainable parameters (policy, and critic for PPO).

    The reference policy of a GRPO loss is a frozen copy (no gradient), so it is left out.

    Example:
        >>> from omegaconf import OmegaConf
        >>> opt = make_optimizer(OmegaConf.create({"lr": 1e-3, "weight_decay": 0.0,
        ...                                       "eps": 1e-8}), torch.nn.Linear(2, 2))
        >>> type(opt).__name__
        'Adam'
    """
    params = [p for p in loss.parameters() if p.requires_grad]
    return torch.optim.Adam(
        params,
        lr=float(optim_cfg.lr),
        weight_decay=float(optim_cfg.weight_decay),
        eps=float(optim_cfg.eps),
    )
