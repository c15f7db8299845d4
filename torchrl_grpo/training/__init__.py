"""Hydra-configured training: builders per config group, the loop, evaluation, checkpoints.

``scripts/train.py`` and ``scripts/evaluate.py`` are thin wrappers around this
package. Nothing in the rest of the library imports it.
"""

from torchrl_grpo.training.checkpoint import load_checkpoint, save_checkpoint
from torchrl_grpo.training.collect import (
    collector_state,
    env_frames,
    load_collector_state,
    make_collector,
)
from torchrl_grpo.training.config import (
    AlgoConfig,
    Config,
    EnvConfig,
    ExperimentConfig,
    GRPOConfig,
    LoggerConfig,
    ModelConfig,
    OptimConfig,
    PPOConfig,
    RolloutConfig,
    check_config,
    register_configs,
    to_container,
)
from torchrl_grpo.training.env_builder import make_env, make_layout, make_rollout_env
from torchrl_grpo.training.evaluation import (
    BASELINE_LABELS,
    EvalResult,
    baseline_policy,
    evaluate,
    format_table,
    save_gif,
)
from torchrl_grpo.training.logging_builder import log_metrics, log_video, make_logger
from torchrl_grpo.training.loss_builder import (
    is_grpo,
    make_advantage,
    make_loss,
    make_optimizer,
    make_reference_sync,
)
from torchrl_grpo.training.model_builder import make_net, make_policy, make_value
from torchrl_grpo.training.trainer import PhaseTimer, Trainer, TrainResult, plot_learning_curve

__all__ = [
    "BASELINE_LABELS",
    "AlgoConfig",
    "Config",
    "EnvConfig",
    "EvalResult",
    "ExperimentConfig",
    "GRPOConfig",
    "LoggerConfig",
    "ModelConfig",
    "OptimConfig",
    "PPOConfig",
    "PhaseTimer",
    "RolloutConfig",
    "TrainResult",
    "Trainer",
    "baseline_policy",
    "check_config",
    "collector_state",
    "env_frames",
    "evaluate",
    "format_table",
    "is_grpo",
    "load_checkpoint",
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
    "plot_learning_curve",
    "register_configs",
    "save_checkpoint",
    "save_gif",
    "to_container",
]
