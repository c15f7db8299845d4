"""Who acts on the tails of GRPO's branches, and what a tail cut by the horizon is worth.

A greedy-tail branch explores its first steps, then a tail actor drives it: the learner,
or a scripted base policy (``algo.tail_policy``). A branch the
horizon cuts is credited the episode steps left (``algo.bootstrap``); with
``algo.bootstrap=survival``, times the crash head's probability of surviving them. With
``algo.crash_label=bootstrap``, or with ``algo.bootstrap=survival`` whatever
``algo.crash_label`` says, the same probability labels the head's own training rows of
branches cut alive (:func:`crash_labels` uses it wherever it was built).
"""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from torchrl_grpo.branching.keys import MASK
from torchrl_grpo.objectives.bootstrap import HorizonBootstrap
from torchrl_grpo.objectives.survival import TailSurvival, crash_label
from torchrl_grpo.training.algos.enumerated import branch_crashed
from torchrl_grpo.training.algos.grpo_checks import check_crash_head_needed
from torchrl_grpo.training.model_builder import make_base_policy

__all__ = ["crash_labels", "make_tail_policy", "make_tail_survival"]


def make_tail_policy(algo: DictConfig, policy: nn.Module, env: EnvBase) -> nn.Module | None:
    """The actor of greedy tails when it is not ``policy`` itself, or ``None``.

    A scripted base policy (``algo.tail_policy``); ``None`` for the learner's own tails.
    (The experimental ``algo=grpo_lab`` also has a lagging copy of the learner,
    ``algo.tail_sync_batches``.)

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> algo = OmegaConf.create({"tail_policy": "learner"})
        >>> make_tail_policy(algo, nn.Linear(1, 1), TensorHighwayEnv(num_envs=1)) is None
        True
    """
    base = str(algo.tail_policy)
    if base != "learner":
        return make_base_policy(base, env, "algo.tail_policy")
    return None


def make_tail_survival(algo: DictConfig, head: nn.Module | None) -> TailSurvival | None:
    """The :class:`~torchrl_grpo.objectives.survival.TailSurvival` of ``algo.bootstrap=survival``.

    Also built for ``algo.crash_label=bootstrap``, whose labels it gives.

    Args:
        algo: the ``algo`` config.
        head: the policy's crash head (or its ensemble); ``None`` without one.

    Raises:
        ValueError: ``algo.bootstrap=survival`` or ``algo.crash_label=bootstrap`` without
            a crash head.

    Example:
        >>> from omegaconf import OmegaConf
        >>> make_tail_survival(OmegaConf.create({"bootstrap": "batch_mean"}), None) is None
        True
    """
    check_crash_head_needed(algo, head is not None)
    asked = str(algo.bootstrap) == "survival" or str(algo.get("crash_label")) == "bootstrap"
    return TailSurvival(head) if asked else None


def crash_labels(
    batch: TensorDictBase, bootstrap: HorizonBootstrap, survival: TailSurvival | None
) -> torch.Tensor:
    """``[R, G, T]``: each branch's crash label, on every step of the branch.

    Whether the branch crashed; with ``survival`` (built for ``algo.crash_label=bootstrap``
    and for ``algo.bootstrap=survival``, which so bootstraps the labels even with
    ``algo.crash_label=branch``; after ``survival`` has written its key),
    :func:`~torchrl_grpo.objectives.survival.crash_label`:
    where the horizon cut the branch before its episode's last step
    (:meth:`~torchrl_grpo.objectives.HorizonBootstrap.steps_left` > 0), the head's crash
    probability at its last state.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.modules import CrashHead
        >>> batch = TensorDict({"mask": torch.tensor([[[True, True], [True, True]]]),
        ...                     "root_step": torch.tensor([[[3, 3], [8, 8]]]),
        ...                     "tail_survival": torch.full((1, 2, 2), 0.75),
        ...                     ("next", "terminated"): torch.zeros(1, 2, 2, 1, dtype=bool)},
        ...                    batch_size=[1, 2, 2])
        >>> survival = TailSurvival(CrashHead(nn.Linear(1, 4), 2))
        >>> labels = crash_labels(batch, HorizonBootstrap(10), survival)
        >>> labels.tolist()  # the second branch ends at the episode's step limit, 10
        [[[0.25, 0.25], [0.0, 0.0]]]
    """
    crashed = branch_crashed(batch, MASK)
    if survival is None:
        return crashed
    mask = batch.get(MASK)
    cut = (bootstrap.steps_left(batch) > 0).unsqueeze(-1)
    alive = batch.get(survival.tensor_keys.survival).reshape(mask.shape)
    return crash_label(crashed, cut, alive.float())
