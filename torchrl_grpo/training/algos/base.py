"""What an algorithm is to the trainer, and the registry that names them.

An algorithm is one file of this package: its config dataclass (a subclass of
:class:`AlgoConfig`), its builders (loss, advantage, ...), its collector, its update
of a batch and its batch metrics, in a subclass of :class:`Algorithm` registered with
:func:`register_algorithm`. The registry feeds Hydra's ConfigStore
(:func:`~torchrl_grpo.training.register_configs` stores each schema as
``algo/<config_name>``), so ``conf/algo/<name>.yaml`` starting from that schema is
all the config an algorithm adds. See ``docs/training.md`` for a worked example.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from omegaconf import MISSING, DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import BaseCollector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import LossModule

from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.modules.ensemble import PolicyEnsemble
from torchrl_grpo.modules.forward_sharing import shared_forward
from torchrl_grpo.training.algos.member_terms import mean_member_terms
from torchrl_grpo.training.collect import make_collector
from torchrl_grpo.training.env_builder import make_rollout_env
from torchrl_grpo.training.group_schemas import (
    MODEL_SCHEMAS,
    ModelConfig,
    StepRolloutConfig,
    collects_on_ray,
)
from torchrl_grpo.training.metrics import PhaseTimer, metric_name
from torchrl_grpo.training.model_builder import NETWORK_KINDS
from torchrl_grpo.training.optim_builder import make_optimizer
from torchrl_grpo.training.retired_keys import SHARED_FIXED, with_fixed

__all__ = ["AlgoConfig", "Algorithm"]


@dataclass
class AlgoConfig:
    """``algo`` group: fields every algorithm has.

    Each algorithm's schema extends it (:class:`~torchrl_grpo.training.GRPOConfig`,
    :class:`~torchrl_grpo.training.PPOConfig`) and types ``name`` with its own choices.

    Example:
        >>> from torchrl_grpo.training import Config, PPOConfig
        >>> cfg = OmegaConf.structured(Config)
        >>> cfg.algo = PPOConfig(name="ppo")
        >>> OmegaConf.get_type(cfg.algo).__name__, cfg.algo.epochs, cfg.algo.minibatch_size
        ('PPOConfig', 4, 256)
        >>> try:
        ...     cfg.algo.name = "sac"  # not a name of PPO
        ... except Exception as err:
        ...     print(type(err).__name__)
        ValidationError
    """

    name: str = MISSING
    entropy_coeff: float = 0.01
    epochs: int = 4
    minibatch_size: int = 256


class Algorithm:
    """One training algorithm: what it builds from the config, collects and updates.

    A subclass sets the class attributes and implements :meth:`make_loss` and
    :meth:`update`; everything else has a default. The trainer builds it after the
    policy (``algo(cfg, policy, env)``) and, each iteration, calls
    :meth:`batch_metrics`, :meth:`update` and :meth:`after_batch` on the batch its
    collector (:meth:`make_collector`) delivers. :meth:`state_dict` is its part of a
    checkpoint.

    Its class attributes: ``names``, the values of ``algo.name`` it runs;
    ``config_class``, its schema (a subclass of :class:`AlgoConfig`); ``config_name``,
    the schema's name in Hydra's ConfigStore, which the defaults of
    ``conf/algo/<name>.yaml`` start from; ``supports_ray``, whether it collects with
    ``rollout=ray``; ``trains_crash_head``, whether it trains a
    ``model.crash_head``; ``has_groups``, whether its batches carry group ids
    (``model.bagging`` splits them between ensemble members).

    Args:
        cfg: the composed config.
        policy: the policy being trained.
        env: an env of the scenario in this process, for specs.

    Example:
        >>> from torchrl_grpo.training import Algorithm
        >>> from torchrl_grpo.training.algos.registry import algorithm_for
        >>> cls = algorithm_for(OmegaConf.create({"name": "grpo_episode"}))
        >>> cls.__name__, cls.config_name, issubclass(cls, Algorithm)
        ('GRPO', 'base_grpo', True)
    """

    names: ClassVar[tuple[str, ...]] = ()
    config_class: ClassVar[type[AlgoConfig]] = AlgoConfig
    config_name: ClassVar[str] = ""
    rollout_config_class: ClassVar[type] = StepRolloutConfig
    supports_ray: ClassVar[bool] = False
    trains_crash_head: ClassVar[bool] = False
    has_groups: ClassVar[bool] = False

    def __init__(self, cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase) -> None:
        cfg = self.with_fixed_settings(cfg)
        self.cfg = cfg
        self.policy = policy
        self.env = env
        #: The policy's ``PolicyEnsemble`` (``model.ensemble > 1``), else ``None``.
        self.ensemble = next((m for m in policy.modules() if isinstance(m, PolicyEnsemble)), None)
        #: What a crash head's loss trains (``model.crash_head``), else ``None``: the
        #: policy's ``CrashHead``, or its ensemble, which answers for its active member
        #: (:meth:`member_terms`).
        self.trained_head: torch.nn.Module | None = next(
            (m for m in policy.modules() if isinstance(m, CrashHead)), None
        )
        if self.trained_head is not None and self.ensemble is not None:
            self.trained_head = self.ensemble
        # The value network draws its initial weights right after the policy's.
        self.value = self.make_value(cfg.model, env)
        if self.value is not None:
            self.value = self.value.to(self.device)
        self.loss = self.make_loss(cfg.algo, policy, self.value).to(self.device)
        self.optimizer = make_optimizer(cfg.optim, self.loss)
        self.updates = 0

    @property
    def device(self) -> torch.device:
        """Where the policy's weights are (``cfg.device``): the learner's batches go there."""
        return next(self.policy.parameters()).device

    # ---------------------------------------------------------------- schemas
    @classmethod
    def fixed_settings(cls, name: str) -> dict[str, dict[str, Any]]:
        """``{group: {key: value}}``: what a run of ``algo.name=name`` uses for keys it lacks.

        The recipe's values of settings that are not keys of the algorithm's schema
        (:mod:`~torchrl_grpo.training.retired_keys`); the code reads them from the
        config :func:`with_fixed_settings` completes.
        """
        return {}

    @classmethod
    def with_fixed_settings(cls, cfg: DictConfig) -> DictConfig:
        """The config a run of this algorithm executes: ``cfg`` plus its fixed settings.

        The keys a composed config has are what a user sets; the settings the
        recommended recipe fixes (:meth:`fixed_settings` and
        :data:`~torchrl_grpo.training.retired_keys.SHARED_FIXED`) are filled in where
        the config lacks them. Idempotent; the result is a plain (untyped) config.
        """
        container = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
        name = (container.get("algo") or {}).get("name")
        if name is not None:
            container = with_fixed(container, cls.fixed_settings(str(name)))
        return OmegaConf.create(with_fixed(container, SHARED_FIXED))

    @classmethod
    def algo_with_fixed(cls, algo_cfg: DictConfig) -> DictConfig:
        """An ``algo`` config with the settings :meth:`fixed_settings` gives it filled in."""
        algo = OmegaConf.to_container(algo_cfg, resolve=True, enum_to_str=True)
        fixed = cls.fixed_settings(str(algo["name"])).get("algo", {})
        return OmegaConf.create({**fixed, **algo})

    @classmethod
    def model_schema(cls, kind: str) -> type[ModelConfig]:
        """The ``model`` schema of a network ``kind`` for this algorithm.

        A kind beside the core's has the schema it was registered with
        (:func:`~torchrl_grpo.training.model_builder.register_network_kind`).

        Raises:
            ValueError: ``kind`` is neither a core kind nor registered.
        """
        if kind in MODEL_SCHEMAS:
            return MODEL_SCHEMAS[kind]
        registered = NETWORK_KINDS.get(kind)
        if registered is None:
            core = ", ".join(MODEL_SCHEMAS)
            raise ValueError(
                f"model.kind={kind!r} is not a network kind of the core ({core}); the lab's "
                "kinds are registered by 'import torchrl_grpo.experimental' and run with "
                "algo=grpo_lab model=lab"
            )
        return registered[1]

    @classmethod
    def extra_schemas(cls) -> dict[str, type]:
        """``{group: schema}`` the algorithm registers beside its ``algo`` schema."""
        return {}

    # ---------------------------------------------------------------- builders
    @classmethod
    def make_value(cls, model_cfg: DictConfig, env: EnvBase) -> ValueOperator | None:
        """The critic (``None``: the algorithm has none)."""
        return None

    @classmethod
    def make_loss(
        cls, algo_cfg: DictConfig, policy: ProbabilisticActor, value: ValueOperator | None = None
    ) -> LossModule:
        """The loss module, over the policy (and the critic)."""
        raise NotImplementedError(f"{cls.__name__} builds no loss")

    @classmethod
    def make_advantage(
        cls, algo_cfg: DictConfig, value: ValueOperator | None = None
    ) -> TensorDictModuleBase | None:
        """The advantage module (``None``: the update computes its own)."""
        return None

    @classmethod
    def make_reference_sync(cls, algo_cfg: DictConfig, loss: LossModule) -> Any | None:
        """The reference-policy updater of the loss (``None``: no reference)."""
        return None

    @classmethod
    def check_config(cls, cfg: DictConfig) -> None:
        """Refuses relations between keys that types alone cannot express.

        Raises:
            ValueError: naming the offending key.
        """
        rollout = cfg.get("rollout")
        if not cls.supports_ray and collects_on_ray(rollout):
            raise ValueError(f"rollout=ray collects GRPO groups; algo={cfg.algo.name} is not GRPO")
        cap = cfg.algo.get("max_minibatches")
        if cap is not None and cap < 1:
            raise ValueError(f"algo.max_minibatches must be >= 1 (or null), got {cap}")
        model = cfg.get("model")
        if model is not None and model.get("bagging", False):
            if int(model.get("ensemble", 1)) < 2 or not cls.has_groups:
                raise ValueError(
                    "model.bagging gives each ensemble member its own half of the groups: it "
                    f"needs model.ensemble >= 2 (got {model.get('ensemble', 1)}) and an algo "
                    f"with branch groups (got algo={cfg.algo.name})"
                )
        if model is not None and model.get("crash_head", False):
            if not cls.trains_crash_head:
                raise ValueError(
                    f"model.crash_head is trained on the crashes of enumerated branch groups, "
                    f"or on teachers' crash heads; algo={cfg.algo.name} has neither (use "
                    "algo=grpo_branch, or algo=distill)"
                )
            coeff = cfg.algo.crash_head_coeff
            if not (coeff > 0 and coeff < math.inf):
                raise ValueError(
                    f"algo.crash_head_coeff must be a finite number > 0 to train "
                    f"model.crash_head, got {coeff}"
                )

    def make_collector(self, seed: int) -> BaseCollector:
        """TorchRL's ``Collector`` of ``rollout.frames_per_batch`` steps over the workers.

        The workers write their simulator state after each step, so that a checkpoint
        restores them mid-episode (:func:`~torchrl_grpo.training.collect.collector_state`).
        """
        cfg = self.cfg
        env = make_rollout_env(
            cfg.env, cfg.rollout, snapshots=False, return_state=True, device=cfg.device, seed=seed
        )
        exploration = self.trunk_exploration(cfg.algo)
        return make_collector(cfg, env, self.policy, seed=seed, trunk_exploration=exploration)

    @classmethod
    def trunk_exploration(cls, algo_cfg: DictConfig) -> ExplorationType:
        """How the policy acts on the worlds it drives (trunks): it samples."""
        return ExplorationType.RANDOM

    # ---------------------------------------------------------------- per batch
    def batch_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        """What the collected batch shows (``collect/`` metrics)."""
        return {}

    def update(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """Learn from a batch; the metrics of the update."""
        raise NotImplementedError(f"{type(self).__name__} has no update")

    def after_batch(self, iteration: int) -> None:
        """Called once the batch of ``iteration`` (counted from 1) is learnt from."""

    def on_optimizer_step(self) -> None:
        """Called after every optimiser step of :meth:`optimise`."""

    def loss_terms(self, minibatch: TensorDictBase) -> TensorDictBase:
        """The loss's output on ``minibatch``: every ``loss_*`` entry is summed and minimised."""
        return self.loss(minibatch)

    def member_terms(self, minibatch: TensorDictBase) -> TensorDictBase:
        """:meth:`loss_terms`, or with ``model.ensemble=K`` the mean of each member's own.

        With ``model.bagging``, each member fits its own half of the groups
        (:func:`~torchrl_grpo.training.algos.member_terms.mean_member_terms`).
        """
        if self.ensemble is None:
            return self.loss_terms(minibatch)
        bagging = bool(self.cfg.model.get("bagging", False))
        return mean_member_terms(self.ensemble, self.loss_terms, minibatch, bagging)

    def optimise(
        self, data: TensorDictBase, refresh: Callable[[], TensorDictBase] | None = None
    ) -> dict[str, float]:
        """``algo.epochs`` passes of shuffled minibatches of ``data`` through the loss.

        With ``algo.max_minibatches=k`` the passes stop after ``k`` minibatches: a
        large replay then gives each batch a random subset of its steps at a fixed cost
        per batch, instead of a cost that grows with the replay.

        Args:
            data: flat training steps.
            refresh: called before every epoch but the first, gives the data of that
                epoch (PPO recomputes its advantages with the updated critic).

        Returns:
            The mean of every scalar the loss returns (``train/<key>``: ``loss_*``
            terms, diagnostics), ``train/loss_total``, ``train/grad_norm``,
            ``train/lr`` and ``train/minibatches``.
        """
        algo = self.cfg.algo
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        data = data.to(self.device)
        n = data.shape[0]
        mb = min(int(algo.minibatch_size), n)
        cap = algo.get("max_minibatches")
        limit = math.inf if cap is None else int(cap)
        sums: dict[str, float] = defaultdict(float)
        count = 0
        for epoch in range(int(algo.epochs)):
            if count >= limit:
                break
            if refresh is not None and epoch > 0:
                data = refresh()
            perm = torch.randperm(n)
            for start in range(0, n - mb + 1, mb):
                if count >= limit:
                    break
                # The losses of one minibatch share the network's forward and backward.
                with shared_forward(self.policy):
                    out = self.member_terms(data[perm[start : start + mb]])
                loss = sum(v for k, v in out.items() if k.startswith("loss_"))
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                grad_norm = torch.nn.utils.clip_grad_norm_(
                    params, float(self.cfg.optim.max_grad_norm)
                )
                self.optimizer.step()
                self.updates += 1
                self.on_optimizer_step()
                for key, value in out.items():
                    if isinstance(value, torch.Tensor) and value.numel() == 1:
                        sums[metric_name(key)] += float(value.detach())
                sums["train/grad_norm"] += float(grad_norm)
                sums["train/loss_total"] += float(loss.detach())
                count += 1
        means = {k: v / max(count, 1) for k, v in sums.items()}
        means["train/lr"] = self.optimizer.param_groups[0]["lr"]
        means["train/minibatches"] = float(count)
        return means

    def counters(self) -> dict[str, int]:
        """Counts of the algorithm's own that every evaluation's row records (none here).

        ``algo=search_distill`` records its search's branch steps, which a result adds
        to the run's frames.
        """
        return {}

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Its part of a checkpoint (top-level keys of the checkpoint's dict)."""
        return {
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            "value": None if self.value is None else self.value.state_dict(),
        }

    def load_state_dict(self, checkpoint: dict[str, Any], source: str = "") -> None:
        """Restores :meth:`state_dict` from a checkpoint (``source``: its path, for errors)."""
        self.loss.load_state_dict(checkpoint["loss"])
        if self.value is not None and checkpoint.get("value") is not None:
            self.value.load_state_dict(checkpoint["value"])
        self.optimizer.load_state_dict(checkpoint["optimizer"])
        self.updates = int(checkpoint["updates"])
