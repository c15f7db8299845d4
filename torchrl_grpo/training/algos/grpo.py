"""GRPO: group-relative advantages of branch groups, ``GRPOLoss``, no critic.

Two variants (``algo.name``): ``grpo_branch`` branches groups from decision points along
trunk episodes, ``grpo_episode`` rolls whole episodes from one reset. A batch is
``[R, G, T]`` (roots, branches, steps).
"""

from __future__ import annotations

import copy
from typing import Any, get_args

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.collectors import BaseCollector
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import LossModule

from torchrl_grpo.branching.keys import GROUP_ID, MASK
from torchrl_grpo.modules.greedy_tail import EXPLORED
from torchrl_grpo.objectives.advantage import GroupRelativeAdvantage
from torchrl_grpo.objectives.bootstrap import HorizonBootstrap
from torchrl_grpo.objectives.crash_head_loss import CrashHeadLoss
from torchrl_grpo.objectives.grpo_loss import GRPOLoss
from torchrl_grpo.objectives.reference import ReferenceSync
from torchrl_grpo.training.algos.base import Algorithm
from torchrl_grpo.training.algos.branch_tails import (
    crash_labels,
    make_tail_policy,
    make_tail_survival,
)
from torchrl_grpo.training.algos.enumerated import (
    BRANCH_CRASHED,
    check_replay_targets,
    distill_targets,
    make_group_fit_loss,
    make_replay,
    policy_weighted,
    replay_rows,
)
from torchrl_grpo.training.algos.grpo_checks import check_grpo_config
from torchrl_grpo.training.algos.grpo_config import (
    FIXED_SETTINGS,
    GRPOConfig,
    GRPOVariant,
)
from torchrl_grpo.training.algos.registry import register_algorithm
from torchrl_grpo.training.collect import make_collector, trunk_schedule
from torchrl_grpo.training.env_builder import episode_step_limit, make_rollout_env
from torchrl_grpo.training.group_schemas import GroupRolloutConfig, collects_on_ray
from torchrl_grpo.training.metrics import PhaseTimer, group_metrics
from torchrl_grpo.training.retired_keys import renamed

__all__ = ["GRPO", "TRAIN_REWARD", "GRPOConfig", "GRPOVariant", "make_replay", "policy_weighted"]

#: The reward GRPO advantages are computed from: the env's reward plus, on the last step
#: of a branch cut by the horizon, the bootstrap of the episode steps left.
TRAIN_REWARD = ("next", "train_reward")
#: Each ensemble member's log-prob of a replayed step's action, ``[N, K]``
#: (``model.ensemble=K``): the "old" log-probs of that member's ratio.
MEMBER_LOG_PROB = "member_action_log_prob"

# Keys the updates read: everything else of a batch (states, positions) is dropped early.
_TRAINED_KEYS = ("observation", "action", "action_log_prob", "advantage", MASK, GROUP_ID, "branch")


@register_algorithm
class GRPO(Algorithm):
    """GRPO on branch groups: the bootstrap, the group-relative advantage and ``GRPOLoss``.

    Builds, beside the loss: the advantage, the horizon bootstrap, the reference sync,
    the actor of greedy tails (a copy of the policy or a base policy) and the replay.

    Example:
        >>> from torchrl_grpo.training import GRPO, compose_config
        >>> cfg = compose_config(["experiment=smoke"])  # greedy tails of the rule policy
        >>> from torchrl_grpo.training import make_env, make_policy
        >>> env = make_env(cfg.env, seed=0)
        >>> grpo = GRPO(cfg, make_policy(cfg.model, env), env)
        >>> type(grpo.loss).__name__, grpo.bootstrap.step_limit, grpo.tail_policy is not None
        ('GRPOLoss', 30, True)
    """

    names = get_args(GRPOVariant)
    config_class = GRPOConfig
    config_name = "base_grpo"
    rollout_config_class = GroupRolloutConfig
    supports_ray = True
    trains_crash_head = True
    has_groups = True

    def __init__(self, cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase) -> None:
        super().__init__(cfg, policy, env)
        cfg = self.cfg  # with the settings the variant fixes
        algo = cfg.algo
        self.advantage = self.make_advantage(algo)
        self.bootstrap = HorizonBootstrap(
            episode_step_limit(env, int(cfg.env.max_episode_steps)),
            str(algo.bootstrap),
            termination_penalty=float(algo.crash_penalty),
        ).set_keys(train_reward=TRAIN_REWARD)
        self.ref_sync = self.make_reference_sync(algo, self.loss)
        self.tail_policy = self.make_tail_policy(algo, policy, env)
        self.replay = make_replay(algo, self.trained_branches(algo))
        self.distill = make_group_fit_loss(algo, policy)
        head = self.trained_head
        self.crash_head = (
            None if head is None else CrashHeadLoss(head, coeff=float(algo.crash_head_coeff))
        )
        self.tail_survival = make_tail_survival(algo, head)

    @classmethod
    def fixed_settings(cls, name: str) -> dict[str, dict[str, Any]]:
        """The recipe's values of the variant's settings that are not keys (see GRPOConfig)."""
        return copy.deepcopy(FIXED_SETTINGS.get(name, {}))

    @classmethod
    def make_tail_policy(
        cls, algo_cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase
    ) -> torch.nn.Module | None:
        """The actor of greedy tails when it is not the policy itself, or ``None``.

        A scripted base policy (``algo.tail_policy``); it is part of the checkpoint when
        it has parameters (the experimental lagging copy of the policy).
        """
        return make_tail_policy(algo_cfg, policy, env)

    @classmethod
    def make_loss(
        cls, algo_cfg: DictConfig, policy: ProbabilisticActor, value: ValueOperator | None = None
    ) -> GRPOLoss:
        """``GRPOLoss`` with the clip range, KL term, entropy bonus and aggregation of ``algo``."""
        kl = algo_cfg.kl_to_ref_coeff
        return GRPOLoss(
            policy,
            clip_epsilon=(float(algo_cfg.clip_epsilon_low), float(algo_cfg.clip_epsilon_high)),
            dual_clip=algo_cfg.dual_clip,
            kl_to_ref_coeff=None if kl is None else float(kl),
            kl_estimator=str(algo_cfg.kl_estimator),
            entropy_bonus=float(algo_cfg.entropy_coeff) > 0,
            entropy_coeff=float(algo_cfg.entropy_coeff),
            aggregation=str(algo_cfg.aggregation),
        )

    @classmethod
    def make_advantage(
        cls, algo_cfg: DictConfig, value: ValueOperator | None = None
    ) -> GroupRelativeAdvantage:
        """The group-relative advantage of the training reward (:data:`TRAIN_REWARD`)."""
        # The env's reward stays untouched for the metrics; the bootstrap writes its own.
        return GroupRelativeAdvantage(
            returns=str(algo_cfg.returns),
            baseline=str(algo_cfg.baseline),
            scale_rewards=str(algo_cfg.scale_rewards),
            gamma=float(algo_cfg.gamma),
        ).set_keys(reward=TRAIN_REWARD)

    @classmethod
    def make_reference_sync(cls, algo_cfg: DictConfig, loss: LossModule) -> ReferenceSync | None:
        """The reference updater, or ``None`` without a KL term or with a frozen reference.

        ``algo.ref_model_sync_steps=null`` keeps the reference frozen at the initial
        policy: with ``model.prior``, the KL then holds the learner to the base policy.
        """
        if algo_cfg.kl_to_ref_coeff is None or algo_cfg.ref_model_sync_steps is None:
            return None
        return ReferenceSync(
            loss,
            ref_model_sync_steps=int(algo_cfg.ref_model_sync_steps),
            ref_model_mixup_alpha=float(algo_cfg.ref_model_mixup_alpha),
        )

    @classmethod
    def check_config(cls, cfg: DictConfig) -> None:
        """Greedy tails, replay and Ray: the relations between keys types cannot express."""
        super().check_config(cfg)
        check_grpo_config(cfg)

    def make_collector(self, seed: int) -> BaseCollector:
        """A ``GroupCollector`` (``RayGroupCollector`` with ``rollout=ray``)."""
        cfg = self.cfg
        env = None
        if not collects_on_ray(cfg.rollout):
            # With the Ray backend every actor builds its own env workers.
            env = make_rollout_env(
                cfg.env, cfg.rollout, snapshots=True, device=cfg.device, seed=seed
            )
        schedule = self.trunk_schedule(cfg.rollout, self.bootstrap.step_limit)
        stagger, min_steps, max_steps = schedule
        return make_collector(
            cfg,
            env,
            self.policy,
            seed=seed,
            tail_policy=self.tail_policy,
            trunk_stagger=stagger,
            trunk_max_steps=max_steps,
            trunk_min_steps=min_steps,
            trunk_exploration=self.trunk_exploration(cfg.algo),
            learner_branches=self.learner_branches(cfg.algo),
        )

    @classmethod
    def learner_branches(cls, algo_cfg: DictConfig) -> int | None:
        """The branches of a group that take ``algo.tail_learner_steps``: all (``None``)."""
        return None

    @classmethod
    def trained_branches(cls, algo_cfg: DictConfig) -> int:
        """How many of a group's branches the update trains on: all of them."""
        return int(algo_cfg.group_size)

    @classmethod
    def trunk_schedule(cls, rollout: DictConfig, step_limit: int) -> tuple[int, int, int | None]:
        """Where trunks have decision points (``training.collect.trunk_schedule``)."""
        return trunk_schedule(rollout, step_limit)

    def batch_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        """Statistics of a ``[R, G, T]`` batch of branch groups."""
        return group_metrics(batch)

    def update(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """Bootstrap, advantage, the trained steps (and replay), then the epochs."""
        with timer("advantage"):
            if self.tail_survival is not None:
                self.tail_survival(batch)
            self.bootstrap(batch)
            self.advantage(batch)
            if self.crash_head is not None:
                batch.set(BRANCH_CRASHED, self.crash_targets(batch))
            data = batch.select(*_TRAINED_KEYS, EXPLORED, BRANCH_CRASHED, strict=False)
            data = data.reshape(-1)
            train = data.get(MASK)
            if EXPLORED in data.keys():
                # Greedy-tail steps score the sampled ones; their actions were not sampled.
                train = train & data.get(EXPLORED)
            data = data[train]
            if self.distill is not None:
                algo = self.cfg.algo
                data = distill_targets(
                    data,
                    float(algo.group_fit_temperature),
                    str(algo.group_fit_weighting),
                    str(algo.group_fit_loss),
                )
        adv = data.get("advantage")
        shape = batch.get(MASK).shape
        stats = {
            "train/advantage_mean": float(adv.mean()),
            "train/advantage_std": float(adv.std()) if adv.numel() > 1 else 0.0,
            "train/advantage_abs_mean": float(adv.abs().mean()),
            "train/advantage_nonzero_fraction": float((adv != 0).float().mean()),
            "collect/group_bootstrap_mean": float(
                batch.get("bootstrap").reshape(shape).sum(-1).mean()
            ),
        }
        if self.tail_survival is not None:
            survival = batch.get(self.tail_survival.tensor_keys.survival)[..., 0]
            stats["train/tail_survival_mean"] = float(survival.mean())
        if self.replay is not None:
            data = self.replayed(data)
            stats["train/replay_steps"] = float(data.shape[0])
        if str(self.cfg.algo.action_weights) == "policy":
            data = policy_weighted(data, int(self.env.action_spec.n))
        with timer("update"):
            stats.update(self.optimise(data))
        return stats

    def crash_targets(self, batch: TensorDictBase) -> torch.Tensor:
        """``[R, G, T]``: what the crash head learns of each branch (:func:`crash_labels`)."""
        return crash_labels(batch, self.bootstrap, self.tail_survival)

    def replayed(self, data: TensorDictBase) -> TensorDictBase:
        """This batch's trained steps plus the replayed ones, log-probs of the current policy.

        With enumerated first actions and a scripted tail, a step's advantage compares
        every action under a fixed base policy: it does not depend on the policy that
        collected it, so old groups stay valid targets (DAgger's aggregated dataset).
        The "old" log-probs of the clipped ratio are the current policy's, so each
        update is a trust region around the policy it starts from.
        """
        self.replay.extend(data.exclude("action_log_prob"))
        return self.current_log_probs(self.replay[:].to(self.device))  # stored on the CPU

    def current_log_probs(self, data: TensorDictBase) -> TensorDictBase:
        """``data`` with the current policy's ``action_log_prob`` of each step's action.

        With ``model.ensemble=K``, each member's own log-probs too
        (:data:`MEMBER_LOG_PROB`, ``[N, K]``): a member's ratio is then taken around
        itself, as it would be alone, not around the ensemble.
        """
        inputs = data.select(*self.policy.in_keys).clone()
        action = data.get("action")
        with torch.no_grad():
            data.set("action_log_prob", self.policy.get_dist(inputs).log_prob(action))
            if self.ensemble is not None:
                members = []
                for member in range(len(self.ensemble)):
                    with self.ensemble.acting(member):
                        members.append(self.policy.get_dist(inputs).log_prob(action))
                data.set(MEMBER_LOG_PROB, torch.stack(members, -1))
        return data

    def loss_terms(self, minibatch: TensorDictBase) -> TensorDictBase:
        """The GRPO loss's terms, with ``loss_distill`` and ``loss_crash_head`` when on."""
        if self.ensemble is not None and self.ensemble.active is not None:
            if MEMBER_LOG_PROB in minibatch.keys():
                own = minibatch.get(MEMBER_LOG_PROB)[..., self.ensemble.active]
                minibatch = minibatch.clone(False).set("action_log_prob", own)
        out = self.loss(minibatch)
        if self.distill is not None:
            out.update(self.distill(minibatch))
        if self.crash_head is not None:
            out.update(self.crash_head(minibatch))
        return out

    def on_optimizer_step(self) -> None:  # noqa: D102
        if self.ref_sync is not None:
            self.ref_sync.step()

    def state_dict(self) -> dict[str, Any]:  # noqa: D102
        return {
            **super().state_dict(),
            "tail_policy": None if self.tail_policy is None else self.tail_policy.state_dict(),
            "replay": None if self.replay is None else self.replay.state_dict(),
            "ref_sync_counter": None if self.ref_sync is None else self.ref_sync.counter,
        }

    def load_state_dict(self, checkpoint: dict[str, Any], source: str = "") -> None:  # noqa: D102
        super().load_state_dict(checkpoint, source)
        if self.tail_policy is not None and checkpoint.get("tail_policy") is not None:
            self.tail_policy.load_state_dict(checkpoint["tail_policy"])
        if self.replay is not None and checkpoint.get("replay") is not None:
            # The saved run's settings, in today's names, with those its variant fixes.
            saved_algo = self.algo_with_fixed(
                OmegaConf.create(renamed("algo", checkpoint["config"]["algo"]))
            )
            check_replay_targets(saved_algo, self.cfg.algo, source)
            saved = replay_rows(saved_algo, self.trained_branches(saved_algo))
            if saved != self.replay.storage.max_size:
                # A loaded storage keeps its saved size: the first write past it would fail.
                raise ValueError(
                    f"resume={source} replays {saved} trained steps and this config "
                    f"{self.replay.storage.max_size}: resume with the run's algo.replay_groups, "
                    "algo.group_size and algo.explore_steps"
                )
            self.replay.load_state_dict(checkpoint["replay"])
        if self.ref_sync is not None and checkpoint.get("ref_sync_counter") is not None:
            self.ref_sync.counter = int(checkpoint["ref_sync_counter"])
