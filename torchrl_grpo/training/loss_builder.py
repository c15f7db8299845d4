"""The loss, advantage and reference builders of the ``algo`` group, by algorithm.

Each algorithm builds its own (:meth:`~torchrl_grpo.training.Algorithm.make_loss`, ...,
in its file of :mod:`~torchrl_grpo.training.algos`); these functions pick the
algorithm of ``algo.name`` and call its builder, as they did before the algorithms
had files of their own.
"""

from __future__ import annotations

from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import LossModule

from torchrl_grpo.objectives.reference import ReferenceSync
from torchrl_grpo.training.algos.grpo import GRPO, TRAIN_REWARD
from torchrl_grpo.training.algos.registry import algorithm_for
from torchrl_grpo.training.optim_builder import make_optimizer

__all__ = [
    "TRAIN_REWARD",
    "is_grpo",
    "make_advantage",
    "make_loss",
    "make_optimizer",
    "make_reference_sync",
]


def is_grpo(algo_cfg: DictConfig) -> bool:
    """Whether ``algo.name`` is one of the critic-free GRPO variants.

    Example:
        >>> from omegaconf import OmegaConf
        >>> is_grpo(OmegaConf.create({"name": "ppo"}))
        False
    """
    return str(algo_cfg.name) in GRPO.names


def make_loss(
    algo_cfg: DictConfig, policy: ProbabilisticActor, value: ValueOperator | None = None
) -> LossModule:
    """The loss of ``algo.name``: ``GRPOLoss`` for GRPO, ``ClipPPOLoss`` (with ``value``) for PPO.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.config import GRPOConfig
        >>> from torchrl_grpo.training.group_schemas import MLPModelConfig
        >>> from torchrl_grpo.training.model_builder import make_policy
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> policy = make_policy(OmegaConf.structured(MLPModelConfig), HighwayEnv(seed=0))
        >>> loss = make_loss(OmegaConf.structured(GRPOConfig(name="grpo_branch")), policy)
        >>> type(loss).__name__, loss.aggregation
        ('GRPOLoss', 'dapo')
    """
    algorithm = algorithm_for(algo_cfg)
    return algorithm.make_loss(algorithm.algo_with_fixed(algo_cfg), policy, value)


def make_advantage(
    algo_cfg: DictConfig, value: ValueOperator | None = None
) -> TensorDictModuleBase | None:
    """The advantage of ``algo.name``: group-relative (GRPO) or GAE over ``value`` (PPO).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.training.config import GRPOConfig
        >>> adv = make_advantage(OmegaConf.structured(GRPOConfig(name="grpo_branch")))
        >>> adv.returns, adv.in_keys[2]
        ('branch', ('next', 'train_reward'))
    """
    algorithm = algorithm_for(algo_cfg)
    return algorithm.make_advantage(algorithm.algo_with_fixed(algo_cfg), value)


def make_reference_sync(algo_cfg: DictConfig, loss: LossModule) -> ReferenceSync | None:
    """The reference-policy updater of ``algo.name``'s loss (``None``: none, or frozen).

    ``algo.ref_model_sync_steps=null`` keeps the GRPO reference frozen at the initial
    policy (``None``): with ``model.prior``, the KL then holds the learner to the base policy.

    Example:
        >>> from omegaconf import OmegaConf
        >>> make_reference_sync(OmegaConf.create({"name": "ppo"}), None) is None
        True
    """
    algorithm = algorithm_for(algo_cfg)
    return algorithm.make_reference_sync(algorithm.algo_with_fixed(algo_cfg), loss)
