"""Typed schemas of the Hydra config groups, registered in Hydra's ConfigStore.

Every group of ``conf/`` (``env``, ``model``, ``algo``, ``rollout``, ``optim``,
``logger``, ``experiment``) is backed by a dataclass here, so a misspelt key, a value
of the wrong type or an unknown choice fails when the config is composed, with
OmegaConf's message naming the full key (``full_key: algo.clip_epsilon``).

String choices are ``str`` enums (OmegaConf rejects ``typing.Literal`` fields); their
members compare equal to their names, so ``cfg.algo.name == "ppo"`` works.

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

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

__all__ = [
    "ActionWeightsName",
    "AggregationName",
    "AlgoConfig",
    "AlgoName",
    "Backend",
    "BaselineName",
    "BootstrapName",
    "Config",
    "EnvConfig",
    "EvalConfig",
    "ExperimentConfig",
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
]


class _Choice(StrEnum):
    """A string choice: equal to its name, printed as its name."""


class AlgoName(_Choice):
    """The training algorithm."""

    grpo_branch = "grpo_branch"
    grpo_episode = "grpo_episode"
    ppo = "ppo"


class RootKindName(_Choice):
    """Where GRPO groups start (see :class:`~torchrl_grpo.branching.GroupCollector`)."""

    trunk = "trunk"
    reset = "reset"
    # "continue" is a Python keyword, and OmegaConf matches enum members by name.
    continuation = "continuation"


class SelectionName(_Choice):
    """Branch selection of ``roots=continue``."""

    best = "best"
    sampled = "sampled"
    trunk = "trunk"


class AggregationName(_Choice):
    """How :class:`~torchrl_grpo.objectives.GRPOLoss` averages over steps."""

    dapo = "dapo"
    bnpo = "bnpo"
    token_mean = "token_mean"
    grpo = "grpo"
    prompt_mean = "prompt_mean"
    dr_grpo = "dr_grpo"


class KLEstimatorName(_Choice):
    """KL estimator of the reference term."""

    k1 = "k1"
    k2 = "k2"
    k3 = "k3"
    analytic = "analytic"


class ReturnsName(_Choice):
    """Per-branch (outcome) or per-step (reward-to-go) group returns."""

    branch = "branch"
    step = "step"


class BaselineName(_Choice):
    """Group baseline: mean (GRPO) or leave-one-out (RLOO)."""

    mean = "mean"
    loo = "loo"


class TrunkPolicyName(_Choice):
    """How the policy acts on the trunks that decision points are taken from."""

    sample = "sample"
    greedy = "greedy"


class FirstActionName(_Choice):
    """How a greedy-tail branch picks its first action (``algo.first_action``)."""

    sample = "sample"
    enumerate = "enumerate"


class ActionWeightsName(_Choice):
    """Weight of each enumerated first action in the objective (``algo.action_weights``).

    ``uniform``: every action of a group counts once, so each advantage moves its
    action's logit by the same amount whatever the policy (the clipped objective over
    the enumerated actions as if they had been sampled). ``policy``: the action's
    advantage is scaled by ``n * pi(a|s)`` (the policy the update starts from), which
    makes the objective the expected clipped surrogate over all actions
    (the all-action policy gradient): a state moves the actions the policy plays.
    """

    uniform = "uniform"
    policy = "policy"


class TailPolicyName(_Choice):
    """Who acts on greedy-tail branches after their explored steps (``algo.tail_policy``).

    ``learner``: the policy being trained (approximate policy iteration; with
    ``algo.tail_sync_batches``, a lagging copy of it). The others are scripted base
    policies (:data:`~torchrl_grpo.modules.SCRIPTED_POLICIES`): the group's returns are
    then the base policy's ``Q(s, a)``, a target that does not move with the learner.
    """

    learner = "learner"
    idle = "idle"
    slower = "slower"
    rule = "rule"
    conservative = "conservative"
    cautious = "cautious"


class PriorName(_Choice):
    """Scripted base policy whose action the policy's logits favour (``model.prior``).

    See :class:`~torchrl_grpo.modules.PriorLogits`; the names are those of
    :data:`~torchrl_grpo.modules.SCRIPTED_POLICIES` that drive deterministically.
    """

    idle = "idle"
    slower = "slower"
    rule = "rule"
    conservative = "conservative"
    cautious = "cautious"


class ScaleRewards(_Choice):
    """Division of the centred returns (TRL's ``scale_rewards``)."""

    group = "group"
    batch = "batch"
    none = "none"


class BootstrapName(_Choice):
    """Value credited to a GRPO branch cut by the horizon (critic-free)."""

    none = "none"
    batch_mean = "batch_mean"


class ModelKind(_Choice):
    """Network over the Kinematics table."""

    mlp = "mlp"
    ego_attention = "ego_attention"
    scene = "scene"


class Backend(_Choice):
    """How the rollout workers run (``ray``: GRPO groups on Ray actors, see ``rollout.ray``)."""

    parallel = "parallel"
    serial = "serial"
    single = "single"
    ray = "ray"


class WorkerBackend(_Choice):
    """How each Ray actor runs its env workers."""

    parallel = "parallel"
    serial = "serial"
    single = "single"


class LoggerBackend(_Choice):
    """Where metrics go."""

    wandb = "wandb"
    csv = "csv"
    none = "none"


class WandbMode(_Choice):
    """wandb's mode: ``offline`` writes a run folder to ``wandb sync`` later."""

    offline = "offline"
    online = "online"


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


@dataclass
class AlgoConfig:
    """``algo`` group: fields every algorithm has.

    The group holds a :class:`GRPOConfig` or a :class:`PPOConfig`.

    Example:
        >>> cfg = OmegaConf.structured(Config)
        >>> cfg.algo = PPOConfig(name="ppo")
        >>> OmegaConf.get_type(cfg.algo).__name__, cfg.algo.epochs, cfg.algo.minibatch_size
        ('PPOConfig', 4, 256)
        >>> try:
        ...     cfg.algo.name = "sac"  # not an AlgoName
        ... except Exception as err:
        ...     print(type(err).__name__)
        ValidationError
    """

    name: AlgoName = MISSING
    entropy_coeff: float = 0.01
    epochs: int = 4
    minibatch_size: int = 256


@dataclass
class GRPOConfig(AlgoConfig):
    """GRPO (``grpo_branch``, ``grpo_episode``): group-relative advantage, no critic.

    Example:
        >>> cfg = OmegaConf.structured(GRPOConfig(name="grpo_branch", group_size=4))
        >>> print(cfg.group_size, cfg.roots, cfg.clip_epsilon_low, cfg.clip_epsilon_high)
        4 trunk 0.2 0.28
        >>> cfg.roots = "reset"  # branch from episode starts
        >>> cfg.roots == "reset"
        True
    """

    group_size: int = 8
    roots: RootKindName = RootKindName.trunk
    select: SelectionName = SelectionName.best
    returns: ReturnsName = ReturnsName.branch
    bootstrap: BootstrapName = BootstrapName.batch_mean
    baseline: BaselineName = BaselineName.mean
    scale_rewards: ScaleRewards = ScaleRewards.group
    gamma: float = 1.0
    clip_epsilon_low: float = 0.2
    clip_epsilon_high: float = 0.28
    dual_clip: float | None = None
    kl_to_ref_coeff: float | None = 0.01
    kl_estimator: KLEstimatorName = KLEstimatorName.k3
    aggregation: AggregationName = AggregationName.dapo
    ref_model_sync_steps: int | None = 64
    ref_model_mixup_alpha: float = 1.0
    explore_steps: int | None = None
    first_action: FirstActionName = FirstActionName.sample
    action_weights: ActionWeightsName = ActionWeightsName.uniform
    tail_sync_batches: int | None = None
    tail_policy: TailPolicyName = TailPolicyName.learner
    replay_groups: int | None = None
    trunk: TrunkPolicyName = TrunkPolicyName.sample


@dataclass
class PPOConfig(AlgoConfig):
    """PPO baseline: TorchRL's ``ClipPPOLoss`` with a value network and GAE.

    Example:
        >>> cfg = OmegaConf.merge(OmegaConf.structured(PPOConfig), {"name": "ppo", "gamma": 0.99})
        >>> cfg.gamma, cfg.lmbda, cfg.clip_epsilon, cfg.loss_critic_type
        (0.99, 0.95, 0.2, 'smooth_l1')
    """

    gamma: float = 0.9
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    critic_coeff: float = 0.5
    normalize_advantage: bool = True
    loss_critic_type: str = "smooth_l1"


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


@dataclass
class LoggerConfig:
    """``logger`` group: TorchRL logger backend and media.

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training import make_logger
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
    baselines: list[str] = field(default_factory=lambda: ["random", "idle", "slower", "rule"])
    checkpoint_every: int = 10
    plot_every: int = 10
    progress_bar: bool = True
    out_dir: str | None = None


@dataclass
class Config:
    """The whole training config (``conf/config.yaml``).

    Example:
        >>> import pathlib
        >>> from hydra import compose, initialize_config_dir
        >>> import torchrl_grpo
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
    resume: str | None = None


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


_GROUP_SCHEMAS: dict[str, dict[str, type]] = {
    "env": {"base_env": EnvConfig},
    "model": {"base_model": ModelConfig},
    "algo": {"base_grpo": GRPOConfig, "base_ppo": PPOConfig},
    "rollout": {"base_rollout": RolloutConfig},
    "optim": {"base_optim": OptimConfig},
    "logger": {"base_logger": LoggerConfig},
    "experiment": {"base_experiment": ExperimentConfig},
}


def register_configs() -> ConfigStore:
    """Register the schemas: ``base_config`` and ``base_<group>`` in each group.

    The YAML files of ``conf/`` list their schema first in their defaults, e.g.
    ``conf/algo/ppo.yaml`` starts from ``base_ppo``. Idempotent.

    Returns:
        Hydra's ConfigStore.

    Example:
        >>> cs = register_configs()
        >>> "base_ppo.yaml" in cs.list("algo")
        True
    """
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(name="base_evaluate", node=EvalConfig)
    for group, schemas in _GROUP_SCHEMAS.items():
        for name, node in schemas.items():
            cs.store(group=group, name=name, node=node)
    return cs


def check_config(cfg: DictConfig) -> None:
    """Checks the relations between keys that types alone cannot express.

    Raises:
        ValueError: naming the offending key.

    Example:
        >>> cfg = OmegaConf.structured(Config(rollout=RolloutConfig(horizon=0)))
        >>> try:
        ...     check_config(cfg)
        ... except ValueError as err:
        ...     print(err)
        rollout.horizon must be >= 1, got 0
    """
    positive = {
        "rollout.horizon": 1,
        "rollout.decision_interval": 1,
        "rollout.groups_per_batch": 1,
        "rollout.frames_per_batch": 1,
        "rollout.num_workers": 1,
        "experiment.total_frames": 1,
        "experiment.eval_every": 0,
        "experiment.eval_episodes": 0,
        "experiment.final_eval_episodes": 0,
        "experiment.checkpoint_every": 0,
        "experiment.plot_every": 0,
        "algo.epochs": 1,
        "algo.minibatch_size": 1,
    }
    for key, low in positive.items():
        group, name = key.split(".")
        if OmegaConf.is_missing(cfg, group) or cfg.get(group) is None:
            continue
        node = cfg[group]
        if name not in node or OmegaConf.is_missing(node, name):
            continue
        value = node[name]
        if value is not None and value < low:
            raise ValueError(f"{key} must be >= {low}, got {value}")
    model = cfg.get("model")
    if model is not None and not OmegaConf.is_missing(cfg, "model"):
        weight = model.get("prior_weight")
        if weight is not None and not weight > 0:
            raise ValueError(f"model.prior_weight must be > 0, got {weight}")
    algo = cfg.get("algo")
    if algo is not None and not OmegaConf.is_missing(cfg, "algo"):
        if "group_size" in algo and algo.group_size < 2:
            raise ValueError(f"algo.group_size must be >= 2, got {algo.group_size}")
        tail_sync = algo.get("tail_sync_batches")
        if tail_sync is not None and (tail_sync < 1 or algo.get("explore_steps") is None):
            raise ValueError(
                f"algo.tail_sync_batches={tail_sync}: must be >= 1, and applies to "
                "greedy-tail branches only (set algo.explore_steps too)"
            )
        tail_policy = algo.get("tail_policy")
        if tail_policy is not None and str(tail_policy) != "learner":
            if algo.get("explore_steps") is None or tail_sync is not None:
                raise ValueError(
                    f"algo.tail_policy={tail_policy} is the base policy of greedy-tail "
                    "branches: set algo.explore_steps too (e.g. 1), and leave "
                    "algo.tail_sync_batches null (it refreshes a learner's copy)"
                )
        replay = algo.get("replay_groups")
        if replay is not None:
            if replay < 1:
                raise ValueError(f"algo.replay_groups must be >= 1, got {replay}")
            enumerated = str(algo.get("first_action")) == "enumerate"
            if not enumerated or str(algo.get("tail_policy", "learner")) == "learner":
                raise ValueError(
                    f"algo.replay_groups={replay} replays old groups, which is sound only when "
                    "their advantages do not depend on the policy that collected them: set "
                    "algo.first_action=enumerate and a scripted algo.tail_policy (e.g. rule)"
                )
        first_action = algo.get("first_action")
        weights = algo.get("action_weights")
        if weights is not None and str(weights) != "uniform" and str(first_action) != "enumerate":
            raise ValueError(
                f"algo.action_weights={weights} weighs enumerated first actions: set "
                "algo.first_action=enumerate (sampled actions are already drawn from the "
                "policy)"
            )
        if first_action is not None and str(first_action) != "sample":
            if algo.get("explore_steps") is None:
                raise ValueError(
                    f"algo.first_action={first_action} chooses the first action of "
                    "greedy-tail branches: set algo.explore_steps too (e.g. 1)"
                )
    rollout = cfg.get("rollout")
    if rollout is not None and not OmegaConf.is_missing(cfg, "rollout"):
        if rollout.backend == Backend.single and rollout.num_workers != 1:
            raise ValueError(
                f"rollout.num_workers must be 1 with rollout.backend=single, "
                f"got {rollout.num_workers}"
            )
        if rollout.backend == Backend.ray:
            _check_ray(cfg, rollout)


def _check_ray(cfg: DictConfig, rollout: DictConfig) -> None:
    """The ``rollout.ray`` keys (only read with ``rollout.backend=ray``)."""
    algo = cfg.get("algo")
    if algo is not None and not OmegaConf.is_missing(cfg, "algo"):
        if "group_size" not in algo:
            raise ValueError(
                f"rollout.backend=ray collects GRPO groups; algo={algo.name} is not GRPO"
            )
        tail_policy = algo.get("tail_policy")
        if tail_policy is not None and str(tail_policy) != "learner":
            raise ValueError(
                f"algo.tail_policy={tail_policy} is not supported with rollout.backend=ray "
                "yet; use the parallel, serial or single backend"
            )
    ray = rollout.get("ray")
    if ray is None:
        return
    if ray.num_actors < 1:
        raise ValueError(f"rollout.ray.num_actors must be >= 1, got {ray.num_actors}")
    if ray.num_actors > rollout.groups_per_batch:
        raise ValueError(
            f"rollout.ray.num_actors ({ray.num_actors}) must be <= rollout.groups_per_batch "
            f"({rollout.groups_per_batch}): every actor collects at least one group"
        )
    if ray.num_cpus_per_actor <= 0:
        raise ValueError(
            f"rollout.ray.num_cpus_per_actor must be > 0, got {ray.num_cpus_per_actor}"
        )
    if ray.workers_per_actor < 1:
        raise ValueError(f"rollout.ray.workers_per_actor must be >= 1, got {ray.workers_per_actor}")
    if ray.env_backend == WorkerBackend.single and ray.workers_per_actor != 1:
        raise ValueError(
            f"rollout.ray.workers_per_actor must be 1 with rollout.ray.env_backend=single, "
            f"got {ray.workers_per_actor}"
        )


def to_container(cfg: DictConfig) -> dict:
    """The resolved config as plain Python (enums as strings), for logging and checkpoints.

    Example:
        >>> to_container(OmegaConf.structured(ModelConfig))["kind"]
        'mlp'
    """
    return OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
