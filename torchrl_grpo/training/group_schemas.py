"""The schemas of the ``model`` and ``rollout`` groups, which depend on the network and algorithm.

A network kind has its own ``model`` schema (:data:`MODEL_SCHEMAS`), and an algorithm
its ``rollout`` schema (:attr:`~torchrl_grpo.training.Algorithm.rollout_config_class`):
GRPO's batches are groups of branches, PPO's a number of steps, so a run composes only
the keys its network and algorithm read. ``rollout=ray`` composes the Ray settings.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import DictConfig

from torchrl_grpo.training.choices import Backend, ModelKind

__all__ = [
    "MODEL_SCHEMAS",
    "AttentionModelConfig",
    "GroupRolloutConfig",
    "MLPModelConfig",
    "ModelConfig",
    "RayConfig",
    "RayRolloutConfig",
    "RolloutConfig",
    "StepRolloutConfig",
    "TransformerModelConfig",
    "collects_on_ray",
]


@dataclass
class ModelConfig:
    """``model`` group: what every network kind has; each kind's schema adds its sizes.

    ``model.crash_head`` (a crash probability per action) is trained by GRPO with
    branching, which turns it on (``conf/model/algo/grpo_branch.yaml``).

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.structured(MLPModelConfig)
        >>> print(cfg.kind, cfg.num_cells)
        mlp [256, 256]
        >>> cfg.kind = "scene"  # a ModelKind, compared as a string
        >>> cfg.kind == "scene"
        True
        >>> try:
        ...     cfg.kind = "lstm"
        ... except Exception as err:
        ...     print(type(err).__name__)
        ValidationError
    """

    kind: ModelKind = ModelKind.mlp
    crash_head: bool = False
    crash_aversion: float = 0.0
    crash_margin: float | None = None


@dataclass
class MLPModelConfig(ModelConfig):
    """``model=mlp``, ``model=scene``: an MLP over the table or the scene's features."""

    num_cells: list[int] = field(default_factory=lambda: [256, 256])


@dataclass
class AttentionModelConfig(ModelConfig):
    """``model=ego_attention``: highway-env's ego-attention network."""

    kind: ModelKind = ModelKind.ego_attention
    embed_dim: int = 64
    num_heads: int = 2
    encoder_cells: list[int] = field(default_factory=lambda: [64])
    decoder_cells: list[int] = field(default_factory=lambda: [64, 64])


@dataclass
class TransformerModelConfig(ModelConfig):
    """``model=transformer``: layers of self-attention among the observed vehicles."""

    kind: ModelKind = ModelKind.transformer
    embed_dim: int = 64
    num_heads: int = 4
    layers: int = 2
    width: int = 256


#: Each of the core's network kinds' schema (a registered kind brings its own:
#: :func:`~torchrl_grpo.training.model_builder.register_network_kind`).
MODEL_SCHEMAS: dict[str, type[ModelConfig]] = {
    "mlp": MLPModelConfig,
    "scene": MLPModelConfig,
    "ego_attention": AttentionModelConfig,
    "transformer": TransformerModelConfig,
}


@dataclass
class RayConfig:
    """``rollout.ray`` (``rollout=ray``): the actors and the Ray cluster.

    ``groups_per_batch`` groups are split over ``num_actors`` actors; each runs
    ``rollout.num_workers`` env workers with ``rollout.backend``. ``address`` joins a
    cluster (``auto``); else Ray starts on this machine with its cores and a 512 MiB
    object store. Each actor reserves 1 GiB of memory, and a dead actor is replaced up
    to 3 times a batch.
    """

    num_actors: int = 2
    num_cpus_per_actor: float = 1.0
    address: str | None = None


@dataclass
class RolloutConfig:
    """``rollout`` group: the env workers; each algorithm's schema adds its batch shape.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.structured(GroupRolloutConfig(num_workers=2))
        >>> print(cfg.backend, cfg.horizon, cfg.groups_per_batch)
        single 8 8
        >>> "frames_per_batch" in cfg, "ray" in OmegaConf.structured(RayRolloutConfig)
        (False, True)
    """

    num_workers: int = 1
    backend: Backend = Backend.single


@dataclass
class GroupRolloutConfig(RolloutConfig):
    """GRPO's batches: ``groups_per_batch`` groups of branches of ``horizon`` steps."""

    horizon: int = 8
    decision_interval: int = 4
    groups_per_batch: int = 8


@dataclass
class RayRolloutConfig(GroupRolloutConfig):
    """``rollout=ray``: GRPO's groups collected by Ray actors (docs/distributed.md).

    ``num_workers`` and ``backend`` are each actor's env workers and how it runs them
    (``single``, ``serial``, ``parallel``).
    """

    ray: RayConfig = field(default_factory=RayConfig)


@dataclass
class StepRolloutConfig(RolloutConfig):
    """PPO's and the distillation's batches: ``frames_per_batch`` steps over the workers."""

    frames_per_batch: int = 512


def collects_on_ray(rollout: DictConfig | None) -> bool:
    """Whether a ``rollout`` config collects on Ray actors (``rollout=ray``).

    Example:
        >>> from omegaconf import OmegaConf
        >>> collects_on_ray(OmegaConf.structured(RayRolloutConfig))
        True
        >>> collects_on_ray(OmegaConf.structured(GroupRolloutConfig))
        False
    """
    return rollout is not None and rollout.get("ray") is not None
