"""Who acts on the tails of GRPO's branches, and what a tail cut by the horizon is worth.

A greedy-tail branch explores its first steps, then a tail actor drives it: the learner,
a frozen copy of it, or a scripted base policy (``algo.tail_policy``). A branch the
horizon cuts is credited the episode steps left (``algo.bootstrap``); with
``algo.bootstrap=survival``, times the crash head's probability of surviving them.
"""

from __future__ import annotations

import copy

from omegaconf import DictConfig
from torch import nn
from torchrl.envs import EnvBase

from torchrl_grpo.objectives import TailSurvival
from torchrl_grpo.training.algos.grpo_checks import check_survival_bootstrap
from torchrl_grpo.training.model_builder import make_base_policy

__all__ = ["make_tail_policy", "make_tail_survival"]


def make_tail_policy(algo: DictConfig, policy: nn.Module, env: EnvBase) -> nn.Module | None:
    """The actor of greedy tails when it is not ``policy`` itself, or ``None``.

    A scripted base policy (``algo.tail_policy``), or a frozen copy of ``policy``
    (``algo.tail_sync_batches``).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> algo = OmegaConf.create({"tail_policy": "learner", "tail_sync_batches": None})
        >>> make_tail_policy(algo, nn.Linear(1, 1), TensorHighwayEnv(num_envs=1)) is None
        True
    """
    # check_config has refused both settings without explore_steps, and together.
    base = str(algo.tail_policy)
    if base != "learner":
        return make_base_policy(base, env, "algo.tail_policy")
    if algo.tail_sync_batches is None:
        return None
    tail = copy.deepcopy(policy)
    tail.requires_grad_(False)
    return tail


def make_tail_survival(algo: DictConfig, head: nn.Module | None) -> TailSurvival | None:
    """The :class:`~torchrl_grpo.objectives.TailSurvival` of ``algo.bootstrap=survival``.

    Args:
        algo: the ``algo`` config.
        head: the policy's crash head (or its ensemble); ``None`` without one.

    Raises:
        ValueError: ``algo.bootstrap=survival`` without a crash head.

    Example:
        >>> from omegaconf import OmegaConf
        >>> make_tail_survival(OmegaConf.create({"bootstrap": "batch_mean"}), None) is None
        True
    """
    check_survival_bootstrap(algo, head is not None)
    return TailSurvival(head) if str(algo.bootstrap) == "survival" else None
