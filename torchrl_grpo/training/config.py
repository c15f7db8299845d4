"""Typed schemas of the shared Hydra config groups, registered in Hydra's ConfigStore.

Every group of ``conf/`` (``env``, ``model``, ``algo``, ``rollout``, ``optim``,
``logger``, ``experiment``) is backed by a dataclass, so a misspelt key, a value of the
wrong type or an unknown choice fails when the config is composed, with OmegaConf's
message naming the full key (``full_key: algo.clip_epsilon``). The shared groups are
here; each algorithm's ``algo`` schema is in its file of
:mod:`~torchrl_grpo.training.algos` (:class:`~torchrl_grpo.training.GRPOConfig`,
:class:`~torchrl_grpo.training.PPOConfig`), registered with the algorithm.

String choices are ``str`` enums built from the library's ``Literal`` types
(:mod:`~torchrl_grpo.training.choices`; OmegaConf rejects ``Literal`` fields); a member
compares equal to its name, so ``cfg.algo.name == "ppo"`` works.

Example:
    >>> from omegaconf import OmegaConf
    >>> cfg = OmegaConf.structured(GRPOConfig)
    >>> cfg.kl_to_ref_coeff
    0.01
    >>> try:
    ...     cfg.clip_epsilon_low = "wide"
    ... except Exception as err:
    ...     print(type(err).__name__)
    ValidationError
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from torchrl_grpo.training.algos.base import ALGORITHMS, AlgoConfig, algorithm_for
from torchrl_grpo.training.algos.grpo import (
    ActionWeightsName,
    GRPOConfig,
    GRPOVariant,
    TailPolicyName,
    TrunkPolicyName,
)
from torchrl_grpo.training.algos.ppo import PPOConfig, PPOVariant
from torchrl_grpo.training.choices import (
    AggregationName,
    Backend,
    BaselineName,
    BootstrapName,
    EnvBackendName,
    FirstActionName,
    KLEstimatorName,
    LoggerBackend,
    ModelKind,
    PriorName,
    ReturnsName,
    RootKindName,
    ScaleRewards,
    SelectionName,
    WandbMode,
    WorkerBackend,
    choice_enum,
)
from torchrl_grpo.training.config_checks import check_config
from torchrl_grpo.training.resolvers import CONF_DIR, register_resolvers

__all__ = [
    "ActionWeightsName",
    "AggregationName",
    "AlgoConfig",
    "AlgoName",
    "Backend",
    "BaselineName",
    "BootstrapName",
    "CONF_DIR",
    "Config",
    "EnvConfig",
    "EvalConfig",
    "ExperimentConfig",
    "FirstActionName",
    "GRPOConfig",
    "KLEstimatorName",
    "LoggerBackend",
    "LoggerConfig",
    "ModelConfig",
    "ModelKind",
    "OptimConfig",
    "PPOConfig",
    "PriorName",
    "RayConfig",
    "ReturnsName",
    "RolloutConfig",
    "RootKindName",
    "ScaleRewards",
    "SelectionName",
    "TailPolicyName",
    "TrunkPolicyName",
    "WandbMode",
    "WorkerBackend",
    "check_config",
    "register_configs",
    "to_container",
    "typed_config",
]


# Kept for code that names the built-in algorithms; each schema types its own name.
AlgoName = choice_enum(
    "AlgoName", Literal[GRPOVariant, PPOVariant], "The built-in algorithms.", module=__name__
)


@dataclass
class EnvConfig:
    """``env`` group: a highway-env scenario and its config overrides.

    Example:
        >>> cfg = OmegaConf.structured(EnvConfig)
        >>> OmegaConf.is_missing(cfg, "scenario")  # a YAML file of conf/env/ must set it
        True
        >>> cfg = OmegaConf.merge(cfg, {"name": "merge", "scenario": "merge-v0",
        ...                             "config": {"collision_reward": -2.0}})
        >>> cfg.scenario, cfg.config.collision_reward, cfg.max_episode_steps
        ('merge-v0', -2.0, 1000)
    """

    name: str = MISSING
    scenario: str = MISSING
    config: dict[str, Any] = field(default_factory=dict)
    max_episode_steps: int = 1000
    backend: EnvBackendName = EnvBackendName["auto"]
    num_envs: int = 1280


@dataclass
class ModelConfig:
    """``model`` group: the policy (and PPO value) network.

    Example:
        >>> cfg = OmegaConf.structured(ModelConfig)
        >>> print(cfg.kind, cfg.num_cells)
        mlp [256, 256]
        >>> cfg.kind = "ego_attention"  # a ModelKind, compared as a string
        >>> cfg.kind == "ego_attention"
        True
        >>> try:
        ...     cfg.kind = "transformer"
        ... except Exception as err:
        ...     print(type(err).__name__)
        ValidationError
    """

    kind: ModelKind = ModelKind.mlp
    num_cells: list[int] = field(default_factory=lambda: [256, 256])
    embed_dim: int = 64
    num_heads: int = 2
    encoder_cells: list[int] = field(default_factory=lambda: [64])
    decoder_cells: list[int] = field(default_factory=lambda: [64, 64])
    prior: PriorName | None = None
    prior_weight: float = 2.0
    crash_head: bool = False
    crash_aversion: float = 0.0
    ensemble: int = 1
    bagging: bool = False


@dataclass
class RayConfig:
    """``rollout.ray``: the Ray backend (``rollout.backend=ray``, GRPO only).

    ``groups_per_batch`` groups are split over ``num_actors`` actors, each running
    ``workers_per_actor`` env workers with ``env_backend`` (``rollout.num_workers`` and
    ``rollout.backend`` describe the local collector only).
    """

    num_actors: int = 2
    workers_per_actor: int = 1
    env_backend: WorkerBackend = WorkerBackend.single
    num_cpus_per_actor: float = 1.0
    memory_per_actor_mb: int | None = 1024
    address: str | None = None
    num_cpus: int | None = None
    object_store_mb: int = 512
    max_restarts: int = 3


@dataclass
class RolloutConfig:
    """``rollout`` group: how experience is gathered.

    Example:
        >>> cfg = OmegaConf.structured(Config(rollout=RolloutConfig(num_workers=2)))
        >>> print(cfg.rollout.backend, cfg.rollout.horizon, cfg.rollout.ray.num_actors)
        single 8 2
        >>> try:
        ...     check_config(cfg)
        ... except ValueError as err:
        ...     print(err)
        rollout.num_workers must be 1 with rollout.backend=single, got 2
        >>> cfg.rollout.backend = "parallel"
        >>> check_config(cfg)
    """

    horizon: int = 8
    decision_interval: int = 4
    groups_per_batch: int = 8
    live_trunks: bool = False
    stagger_trunks: bool = False
    full_horizon_roots: bool = False
    first_root_step: int = 0
    frames_per_batch: int = 512
    num_workers: int = 1
    backend: Backend = Backend.single
    mp_start_method: str | None = "fork"
    ray: RayConfig = field(default_factory=RayConfig)


@dataclass
class OptimConfig:
    """``optim`` group: Adam and gradient clipping.

    Example:
        >>> cfg = OmegaConf.merge(OmegaConf.structured(OptimConfig),
        ...                       OmegaConf.from_dotlist(["optim.lr=0.001"]).optim)
        >>> cfg.lr, cfg.max_grad_norm, cfg.anneal_lr
        (0.001, 1.0, False)
    """

    lr: float = 5e-4
    weight_decay: float = 0.0
    eps: float = 1e-8
    max_grad_norm: float = 1.0
    anneal_lr: bool = False
    ema_decay: float | None = None


@dataclass
class LoggerConfig:
    """``logger`` group: TorchRL logger backend and media.

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training.logging_builder import make_logger
        >>> cfg = OmegaConf.structured(LoggerConfig(backend="csv"))
        >>> print(cfg.backend, cfg.mode, cfg.video)
        csv offline True
        >>> type(make_logger(cfg, tempfile.mkdtemp(), "demo", {})).__name__
        'CSVLogger'
    """

    backend: LoggerBackend = LoggerBackend.wandb
    mode: WandbMode = WandbMode.offline
    project: str = "torchrl_grpo"
    group: str | None = None
    tags: list[str] = field(default_factory=list)
    video: bool = True
    group_plots: bool = True


@dataclass
class ExperimentConfig:
    """``experiment`` group: budgets and how often to evaluate and checkpoint.

    Example:
        >>> cfg = OmegaConf.structured(ExperimentConfig(total_frames=2000, eval_every=0))
        >>> cfg.total_frames, cfg.eval_every, cfg.baselines
        (2000, 0, ['random', 'idle', 'slower', 'rule'])
    """

    name: str = "default"
    total_frames: int = 30_000
    eval_every: int = 10
    eval_episodes: int = 10
    final_eval_episodes: int = 30
    eval_seed: int = 10_000
    final_eval_seed: int = 20_000
    baselines: list[str] = field(default_factory=lambda: ["random", "idle", "slower", "rule"])
    baseline_cache: str | None = "outputs/baselines"
    transfer_gap: bool = True
    checkpoint_every: int = 10
    plot_every: int = 10
    progress_bar: bool = True
    eval_workers: int | None = None
    out_dir: str | None = None


@dataclass
class Config:
    """The whole training config (``conf/config.yaml``).

    Example:
        >>> import pathlib
        >>> import torchrl_grpo
        >>> from hydra import compose, initialize_config_dir
        >>> conf = pathlib.Path(torchrl_grpo.__file__).parents[1] / "conf"
        >>> _ = register_configs()
        >>> with initialize_config_dir(str(conf), version_base=None):
        ...     cfg = compose("config", ["env=merge", "algo=ppo", "seed=3"])
        >>> OmegaConf.get_type(cfg).__name__, OmegaConf.get_type(cfg.algo).__name__
        ('Config', 'PPOConfig')
        >>> cfg.env.scenario, cfg.seed
        ('merge-v0', 3)
    """

    env: EnvConfig = MISSING
    model: ModelConfig = MISSING
    algo: AlgoConfig = MISSING
    rollout: RolloutConfig = MISSING
    optim: OptimConfig = MISSING
    logger: LoggerConfig = MISSING
    experiment: ExperimentConfig = MISSING
    seed: int = 0
    device: str = "cpu"
    resume: str | None = None
    init_from: str | None = None


@dataclass
class EvalConfig:
    """``scripts/evaluate.py``'s config (``conf/evaluate.yaml``)."""

    env: EnvConfig = MISSING
    checkpoint: str | None = None
    episodes: int = 30
    seed: int | None = None
    baselines: list[str] = field(default_factory=lambda: ["random", "idle", "slower", "rule"])
    video: bool = True
    out_dir: str | None = None
    search_horizon: int = 0
    eval_workers: int | None = None


_SHARED_SCHEMAS: tuple[tuple[str, str, type], ...] = (
    ("env", "base_env", EnvConfig),
    ("model", "base_model", ModelConfig),
    ("rollout", "base_rollout", RolloutConfig),
    ("optim", "base_optim", OptimConfig),
    ("logger", "base_logger", LoggerConfig),
    ("experiment", "base_experiment", ExperimentConfig),
)


def register_configs() -> ConfigStore:
    """Register the schemas: ``base_config``, ``base_evaluate`` and ``base_<group>`` in each group.

    The ``algo`` group gets the schema of every registered algorithm
    (:func:`~torchrl_grpo.training.register_algorithm`). The YAML files of ``conf/`` list
    their schema first in their defaults, e.g. ``conf/algo/ppo.yaml`` starts from
    ``base_ppo``. Registers the resolvers ``conf/`` uses as well
    (:func:`~torchrl_grpo.training.resolvers.register_resolvers`). Idempotent.

    Returns:
        Hydra's ConfigStore.

    Example:
        >>> cs = register_configs()
        >>> "base_ppo.yaml" in cs.list("algo")
        True
    """
    register_resolvers()
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(name="base_evaluate", node=EvalConfig)
    for group, name, node in _SHARED_SCHEMAS:
        cs.store(group=group, name=name, node=node)
    for algorithm in set(ALGORITHMS.values()):
        cs.store(group="algo", name=algorithm.config_name, node=algorithm.config_class)
    return cs


def typed_config(container: Mapping[str, Any]) -> DictConfig:
    """A plain resolved config (a checkpoint's, a run's ``config.yaml``) typed by the schemas.

    The ``algo`` group gets the schema of its algorithm. Older spellings of a choice
    read as today's (``roots: continuation`` is ``continue``).

    Raises:
        omegaconf.errors.ValidationError: a value does not fit its key's type.

    Example:
        >>> cfg = typed_config({"algo": {"name": "grpo_branch", "roots": "continuation"}})
        >>> OmegaConf.get_type(cfg.algo).__name__, str(cfg.algo.roots)
        ('GRPOConfig', 'continue')
    """
    schema = OmegaConf.structured(Config)
    algo = container.get("algo")
    if algo is not None:
        schema.algo = OmegaConf.structured(algorithm_for(algo).config_class)
    return OmegaConf.merge(schema, container)


def to_container(cfg: DictConfig) -> dict:
    """The resolved config as plain Python (enums as strings), for logging and checkpoints.

    Example:
        >>> to_container(OmegaConf.structured(ModelConfig))["kind"]
        'mlp'
    """
    return OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
