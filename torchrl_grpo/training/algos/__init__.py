"""The training algorithms, one file each, and their registry.

``grpo.py`` (``grpo_branch``, ``grpo_episode``), ``ppo.py`` (``ppo``) and ``teacher.py``
(``distill``: trained runs distilled into one policy) are built in.
Every other module of this package is imported with it, so a new algorithm is one
file here (a registered :class:`~torchrl_grpo.training.Algorithm` and its config
dataclass) plus its ``conf/algo/<name>.yaml``; see ``docs/training.md``.
"""

import importlib
import pkgutil

from torchrl_grpo.training.algos.base import (
    ALGORITHMS,
    AlgoConfig,
    Algorithm,
    algorithm_for,
    register_algorithm,
)
from torchrl_grpo.training.algos.grpo import GRPO, GRPOConfig
from torchrl_grpo.training.algos.ppo import PPO, PPOConfig
from torchrl_grpo.training.algos.teacher import DistillConfig, TeacherDistill

__all__ = [
    "ALGORITHMS",
    "GRPO",
    "PPO",
    "AlgoConfig",
    "Algorithm",
    "DistillConfig",
    "GRPOConfig",
    "PPOConfig",
    "TeacherDistill",
    "algorithm_for",
    "register_algorithm",
]

# An algorithm added as a file of this package registers itself when it is imported.
for _module in pkgutil.iter_modules(__path__, f"{__name__}."):
    importlib.import_module(_module.name)
