"""Hydra-configured training: the loop, one file per algorithm, hooks, builders per config group.

``scripts/train.py`` and ``scripts/evaluate.py`` are thin wrappers around this
package. Nothing in the rest of the library imports it.
"""

from torchrl_grpo.training.algos.base import AlgoConfig, Algorithm
from torchrl_grpo.training.algos.grpo import GRPO, GRPOConfig
from torchrl_grpo.training.algos.ppo import PPO, PPOConfig
from torchrl_grpo.training.algos.registry import register_algorithm
from torchrl_grpo.training.algos.teacher_distill import DistillConfig, TeacherDistill
from torchrl_grpo.training.baselines import evaluate_baselines
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.compose import compose_config
from torchrl_grpo.training.config import Config, register_configs
from torchrl_grpo.training.env_builder import make_env
from torchrl_grpo.training.evaluation import evaluate
from torchrl_grpo.training.hooks import Hook
from torchrl_grpo.training.model_builder import make_policy
from torchrl_grpo.training.pretrained import load_run_policy
from torchrl_grpo.training.run_plots import plot_learning_curve
from torchrl_grpo.training.search_eval import search_policy
from torchrl_grpo.training.trainer import Trainer, TrainResult

__all__ = [
    "GRPO",
    "PPO",
    "AlgoConfig",
    "Algorithm",
    "Config",
    "DistillConfig",
    "GRPOConfig",
    "Hook",
    "PPOConfig",
    "TeacherDistill",
    "TrainResult",
    "Trainer",
    "compose_config",
    "evaluate",
    "evaluate_baselines",
    "load_checkpoint",
    "load_run_policy",
    "make_env",
    "make_policy",
    "plot_learning_curve",
    "register_algorithm",
    "register_configs",
    "search_policy",
]
