"""Hydra-configured training: the loop, one file per algorithm, hooks, builders per config group.

``scripts/train.py`` and ``scripts/evaluate.py`` are thin wrappers around this
package. Nothing in the rest of the library imports it.
"""

from torchrl_grpo.training.algos import (
    ALGORITHMS,
    GRPO,
    PPO,
    AlgoConfig,
    Algorithm,
    DistillConfig,
    GRPOConfig,
    PPOConfig,
    TeacherDistill,
    algorithm_for,
    register_algorithm,
)
from torchrl_grpo.training.baselines import evaluate_baselines
from torchrl_grpo.training.checkpoint import load_checkpoint, save_checkpoint
from torchrl_grpo.training.collect import (
    collector_state,
    env_frames,
    load_collector_state,
    make_collector,
    world_steps,
)
from torchrl_grpo.training.compose import compose_config, resume_config
from torchrl_grpo.training.config import (
    Config,
    EnvConfig,
    ExperimentConfig,
    LoggerConfig,
    ModelConfig,
    OptimConfig,
    RolloutConfig,
    check_config,
    register_configs,
    to_container,
    typed_config,
)
from torchrl_grpo.training.env_builder import make_env, make_layout, make_rollout_env
from torchrl_grpo.training.evaluation import (
    BASELINE_LABELS,
    baseline_policy,
    evaluate,
    search_policy,
)
from torchrl_grpo.training.hooks import CheckpointHook, EvaluationHook, GroupPlotHook, Hook
from torchrl_grpo.training.logging_builder import log_metrics, log_video, make_logger
from torchrl_grpo.training.loss_builder import (
    is_grpo,
    make_advantage,
    make_loss,
    make_reference_sync,
)
from torchrl_grpo.training.metrics import PhaseTimer
from torchrl_grpo.training.model_builder import make_net, make_policy, make_value
from torchrl_grpo.training.optim_builder import make_optimizer
from torchrl_grpo.training.plots import plot_comparison, plot_learning_curve, save_gif
from torchrl_grpo.training.pretrained import check_same_env, init_policy, load_run_policy
from torchrl_grpo.training.results import (
    EvalResult,
    compare_paired,
    format_table,
    paired_verdicts,
)
from torchrl_grpo.training.teachers import Teachers, load_teachers
from torchrl_grpo.training.trainer import Trainer, TrainResult
from torchrl_grpo.training.transfer import evaluate_on_tensor, paired_gap, tensor_episodes

__all__ = [
    "ALGORITHMS",
    "AlgoConfig",
    "Algorithm",
    "BASELINE_LABELS",
    "CheckpointHook",
    "Config",
    "DistillConfig",
    "EnvConfig",
    "EvalResult",
    "EvaluationHook",
    "ExperimentConfig",
    "GRPO",
    "GRPOConfig",
    "GroupPlotHook",
    "Hook",
    "LoggerConfig",
    "ModelConfig",
    "OptimConfig",
    "PPO",
    "PPOConfig",
    "PhaseTimer",
    "RolloutConfig",
    "TeacherDistill",
    "Teachers",
    "TrainResult",
    "Trainer",
    "algorithm_for",
    "baseline_policy",
    "check_config",
    "check_same_env",
    "collector_state",
    "compare_paired",
    "compose_config",
    "env_frames",
    "evaluate",
    "evaluate_baselines",
    "evaluate_on_tensor",
    "format_table",
    "init_policy",
    "is_grpo",
    "load_checkpoint",
    "load_run_policy",
    "load_teachers",
    "load_collector_state",
    "log_metrics",
    "log_video",
    "make_advantage",
    "make_collector",
    "make_env",
    "make_layout",
    "make_logger",
    "make_loss",
    "make_net",
    "make_optimizer",
    "make_policy",
    "make_reference_sync",
    "make_rollout_env",
    "make_value",
    "paired_gap",
    "paired_verdicts",
    "plot_comparison",
    "plot_learning_curve",
    "register_algorithm",
    "register_configs",
    "resume_config",
    "save_checkpoint",
    "save_gif",
    "search_policy",
    "tensor_episodes",
    "to_container",
    "typed_config",
    "world_steps",
]
