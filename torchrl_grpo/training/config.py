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
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from torchrl_grpo.training.algos.base import AlgoConfig, Algorithm
from torchrl_grpo.training.algos.grpo import GRPOConfig
from torchrl_grpo.training.algos.ppo import PPOConfig
from torchrl_grpo.training.algos.registry import ALGORITHMS, algorithm_for
from torchrl_grpo.training.choices import EnvBackendName, LoggerBackend
from torchrl_grpo.training.config_checks import check_config
from torchrl_grpo.training.group_schemas import (
    MODEL_SCHEMAS,
    AttentionModelConfig,
    GroupRolloutConfig,
    MLPModelConfig,
    ModelConfig,
    RayConfig,
    RayRolloutConfig,
    RolloutConfig,
    StepRolloutConfig,
    TransformerModelConfig,
)
from torchrl_grpo.training.resolvers import CONF_DIR, register_resolvers
from torchrl_grpo.training.retired_keys import (
    SHARED_FIXED,
    LabRequired,
    migrate,
    with_fixed,
    written_before_retirement,
)

__all__ = [
    "CONF_DIR",
    "AlgoConfig",
    "Config",
    "EnvConfig",
    "EvalConfig",
    "ExperimentConfig",
    "GRPOConfig",
    "LoggerConfig",
    "ModelConfig",
    "OptimConfig",
    "PPOConfig",
    "RolloutConfig",
    "check_config",
    "records_video",
    "register_configs",
    "to_container",
    "typed_config",
]


@dataclass
class EnvConfig:
    """``env`` group: a highway-env scenario and its config overrides.

    Example:
        >>> cfg = OmegaConf.structured(EnvConfig)
        >>> OmegaConf.is_missing(cfg, "scenario")  # a YAML file of conf/env/ must set it
        True
        >>> cfg = OmegaConf.merge(cfg, {"scenario": "merge-v0",
        ...                             "config": {"collision_reward": -2.0}})
        >>> cfg.scenario, cfg.config.collision_reward, cfg.max_episode_steps
        ('merge-v0', -2.0, 1000)
    """

    scenario: str = MISSING
    config: dict[str, Any] = field(default_factory=dict)
    max_episode_steps: int = 1000
    backend: EnvBackendName = EnvBackendName["auto"]
    num_envs: int = 1280


@dataclass
class OptimConfig:
    """``optim`` group: Adam (epsilon 1e-8, no weight decay) and gradient clipping.

    Example:
        >>> cfg = OmegaConf.merge(OmegaConf.structured(OptimConfig),
        ...                       OmegaConf.from_dotlist(["optim.lr=0.001"]).optim)
        >>> cfg.lr, cfg.max_grad_norm, cfg.anneal_lr
        (0.001, 1.0, False)
    """

    lr: float = 5e-4
    max_grad_norm: float = 1.0
    anneal_lr: bool = False
    ema_decay: float | None = None


@dataclass
class LoggerConfig:
    """``logger`` group: TorchRL logger backend.

    ``wandb`` runs offline (a folder to ``wandb sync`` later), ``wandb_online`` streams;
    wandb reads the project, group and tags from ``WANDB_PROJECT`` (``torchrl_grpo``
    when unset), ``WANDB_RUN_GROUP`` and ``WANDB_TAGS``. Every backend but ``none``
    records the final evaluation's first episode (a GIF in the run folder, and a video
    in wandb).

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training.logging_builder import make_logger
        >>> cfg = OmegaConf.structured(LoggerConfig(backend="csv"))
        >>> print(cfg.backend, records_video(cfg))
        csv True
        >>> type(make_logger(cfg, tempfile.mkdtemp(), "demo", {})).__name__
        'CSVLogger'
    """

    backend: LoggerBackend = LoggerBackend.wandb


def records_video(logger_cfg: DictConfig) -> bool:
    """Whether a run with this ``logger`` config records an evaluation episode.

    Example:
        >>> records_video(OmegaConf.create({"backend": "none"}))
        False
    """
    return str(logger_cfg.backend) != LoggerBackend.none.value


@dataclass
class ExperimentConfig:
    """``experiment`` group: budgets and how often to evaluate and checkpoint.

    Each periodic evaluation also plots a batch's most informative branch group (GRPO
    with branching), and the run shows a progress bar when it writes to a terminal.

    Example:
        >>> cfg = OmegaConf.structured(ExperimentConfig(total_frames=2000, eval_every=0))
        >>> cfg.total_frames, cfg.eval_every, cfg.baselines
        (2000, 0, ['random', 'idle', 'slower', 'rule'])
    """

    total_frames: int = 30_000
    eval_every: int = 10
    eval_episodes: int = 10
    final_eval_episodes: int = 30
    eval_seed: int = 10_000
    final_eval_seed: int = 20_000
    baselines: list[str] = field(default_factory=lambda: ["random", "idle", "slower", "rule"])
    baseline_cache: str | None = "outputs/baselines"
    checkpoint_every: int = 10
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
    # A ModelConfig ("schema"), typed by the group's file alone (its kind's schema, or
    # model=lab's): a field typed ModelConfig would hold model.kind to the core's kinds.
    model: Any = field(default=MISSING, metadata={"schema": ModelConfig})
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
    ("model", "base_mlp_model", MLPModelConfig),
    ("model", "base_attention_model", AttentionModelConfig),
    ("model", "base_transformer_model", TransformerModelConfig),
    ("rollout", "base_group_rollout", GroupRolloutConfig),
    ("rollout", "base_ray_rollout", RayRolloutConfig),
    ("rollout", "base_step_rollout", StepRolloutConfig),
    ("optim", "base_optim", OptimConfig),
    ("logger", "base_logger", LoggerConfig),
    ("experiment", "base_experiment", ExperimentConfig),
)


def register_configs() -> ConfigStore:
    """Register the schemas: ``base_config``, ``base_evaluate`` and ``base_<group>`` in each group.

    The ``algo`` group gets the schema of every registered algorithm
    (:func:`~torchrl_grpo.training.register_algorithm`), and an algorithm's own
    ``model`` and ``rollout`` schemas where it has them. The YAML files of ``conf/``
    list their schema first in their defaults, e.g. ``conf/algo/ppo.yaml`` starts from
    ``base_ppo``. Registers the resolvers ``conf/`` uses as well
    (:func:`~torchrl_grpo.training.resolvers.register_resolvers`). Idempotent.

    Returns:
        Hydra's ConfigStore.

    Example:
        >>> cs = register_configs()
        >>> "base_ppo.yaml" in cs.list("algo"), "base_group_rollout.yaml" in cs.list("rollout")
        (True, True)
    """
    register_resolvers()
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(name="base_evaluate", node=EvalConfig)
    for group, name, node in _SHARED_SCHEMAS:
        cs.store(group=group, name=name, node=node)
    for algorithm in set(ALGORITHMS.values()):
        cs.store(group="algo", name=algorithm.config_name, node=algorithm.config_class)
        for group, schema in algorithm.extra_schemas().items():
            cs.store(group=group, name=schema.__name__, node=schema)
    return cs


def _schemas(algorithm: type[Algorithm], container: Mapping[str, Any]) -> dict[str, type]:
    """Each group's schema for a config of ``algorithm``."""
    schemas: dict[str, type] = {"algo": algorithm.config_class}
    model = container.get("model")
    if isinstance(model, Mapping):
        schemas["model"] = algorithm.model_schema(str(model.get("kind", "mlp")))
    rollout = container.get("rollout")
    if isinstance(rollout, Mapping):
        ray = rollout.get("ray") is not None and algorithm.supports_ray
        schemas["rollout"] = RayRolloutConfig if ray else algorithm.rollout_config_class
    shared = (("env", EnvConfig), ("optim", OptimConfig), ("logger", LoggerConfig))
    for group, schema in (*shared, ("experiment", ExperimentConfig)):
        schemas[group] = schema
    return schemas


def _keys(schema: type) -> frozenset[str]:
    return frozenset(OmegaConf.structured(schema).keys())


def typed_config(container: Mapping[str, Any]) -> DictConfig:
    """A plain resolved config (a checkpoint's, a run's ``config.yaml``) typed by the schemas.

    The ``algo`` group gets the schema of its algorithm, ``model`` its kind's and
    ``rollout`` its algorithm's. A config written before keys retired is migrated
    (:func:`~torchrl_grpo.training.retired_keys.migrate`): a GRPO run that used
    values the recipe now fixes, or a network kind beside the core's (``model.kind:
    neighbours``, registered by ``torchrl_grpo.experimental``), reads as an
    ``algo=grpo_lab`` run when ``torchrl_grpo.experimental`` is imported. Older
    spellings of a choice read as today's (``first_action: enumeration`` is ``enumerate``).

    Raises:
        ValueError: a retired key holds a value only ``algo=grpo_lab`` has, or
            ``model.kind`` is not a core kind, and the experimental package is not
            imported (or the algorithm is not GRPO); naming the key.
        omegaconf.errors.ValidationError: a value does not fit its key's type.

    Example:
        >>> cfg = typed_config({"algo": {"name": "grpo_branch", "group_size": 4},
        ...                     "model": {"kind": "scene", "num_cells": [64]}})
        >>> OmegaConf.get_type(cfg.algo).__name__, OmegaConf.get_type(cfg.model).__name__
        ('GRPOConfig', 'MLPModelConfig')
    """
    algo = container.get("algo")
    algorithm = None if algo is None else algorithm_for(algo)
    if algorithm is not None:
        container = _migrated(_restructured(container), algorithm)
        algorithm = algorithm_for(container["algo"])
    schema = OmegaConf.structured(Config)
    if algorithm is not None:
        for group, node in _schemas(algorithm, container).items():
            if group in container:
                schema[group] = OmegaConf.structured(node)
    return OmegaConf.merge(schema, container)


def _restructured(container: Mapping[str, Any]) -> dict[str, Any]:
    """A config written before ``rollout=ray`` and ``logger=wandb_online``, in today's shape.

    ``rollout.backend=ray`` with ``rollout.ray.workers_per_actor`` and ``env_backend``
    is today's ``rollout=ray`` with ``num_workers`` and ``backend`` (the Ray settings
    that are not keys any more go); any other backend ran locally, and its (then always
    written) ``rollout.ray`` goes. ``logger.mode=online`` is ``logger=wandb_online``.
    """
    out = dict(container)
    logger = out.get("logger")
    if isinstance(logger, Mapping) and str(logger.get("mode")) == "online":
        if str(logger.get("backend")) == "wandb":
            out["logger"] = {**logger, "backend": "wandb_online"}
    rollout = out.get("rollout")
    ray = rollout.get("ray") if isinstance(rollout, Mapping) else None
    if not isinstance(ray, Mapping) or "workers_per_actor" not in ray:
        return out
    rollout, ray = dict(rollout), dict(ray)
    workers, backend = ray.pop("workers_per_actor"), ray.pop("env_backend", "single")
    if str(rollout.get("backend")) == "ray":
        ray = {key: value for key, value in ray.items() if key in _keys(RayConfig)}
        rollout |= {"num_workers": workers, "backend": backend, "ray": ray}
    else:
        rollout.pop("ray")
    out["rollout"] = rollout
    return out


def _migrated(container: Mapping[str, Any], algorithm: type[Algorithm]) -> dict[str, Any]:
    """``container`` in today's keys; a GRPO run with values the recipe fixes: ``grpo_lab``."""
    name = str(container["algo"]["name"])
    fixed = {group: dict(values) for group, values in SHARED_FIXED.items()}
    for group, values in algorithm.fixed_settings(name).items():
        fixed.setdefault(group, {}).update(values)
    keys = {group: _keys(schema) for group, schema in _schemas(algorithm, container).items()}
    try:
        out = migrate(container, fixed, keys)
        kind = str((out.get("model") or {}).get("kind", "mlp"))
        if kind in MODEL_SCHEMAS or algorithm is ALGORITHMS.get("grpo_lab"):
            return out
        # A registered network kind is the lab's: the run, with the settings its
        # algorithm fixed, is a grpo_lab run of model=lab.
        container = with_fixed(out, fixed)
        raise LabRequired(
            f"model.kind={kind!r} (a network of torchrl_grpo.experimental): a kind of "
            "model=lab with algo=grpo_lab"
        )
    except LabRequired as err:
        lab = ALGORITHMS.get("grpo_lab")
        if lab is None or not issubclass(lab, algorithm) or lab is algorithm:
            raise ValueError(
                f"{err} (python -c 'import torchrl_grpo.experimental' registers it; "
                "scripts/train.py and scripts/evaluate.py import it)"
            ) from None
        if not written_before_retirement(container, keys):
            # Its missing keys held the values its variant fixes, not the lab's defaults.
            container = with_fixed(container, fixed)
        relabelled = {**container, "algo": {**container["algo"], "name": "grpo_lab"}}
        relabelled["algo"].setdefault("roots", "reset" if name == "grpo_episode" else "trunk")
        keys = {group: _keys(schema) for group, schema in _schemas(lab, relabelled).items()}
        return migrate(relabelled, fixed={}, schema_keys=keys)


def to_container(cfg: DictConfig) -> dict:
    """The resolved config as plain Python (enums as strings), for logging and checkpoints.

    Example:
        >>> to_container(OmegaConf.structured(MLPModelConfig))["kind"]
        'mlp'
    """
    return OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
