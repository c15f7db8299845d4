"""Search distillation (``algo=search_distill``): a network fitted to the search over a run.

The lookahead search over a trained run (every action tried from the state, then the
run's greedy actions for ``algo.horizon - 1`` steps, rows of the tensor simulator; what
``scripts/evaluate.py search_horizon=8`` plays) drives better than the run itself. This
algorithm fits one network to that search: the student drives (TorchRL's
``Collector``, greedily, as it is evaluated), the search labels every state it visits with
each action's branch return and crash flag, the labelled states are kept (up to
``algo.replay_frames``), and each batch trains ``algo.max_minibatches`` minibatches drawn
from all of them through :class:`~torchrl_grpo.objectives.SearchLabelLoss`. It is
DAgger with the search as the expert: the student learns the states it reaches itself.

The student needs ``model.crash_head``: it fits the branches' crash flags and acts on
``policy + model.crash_aversion * log(1 - p_crash)``. A frame is a step of the student's
worlds, as for the other algorithms; the search's branch steps are counted apart
(``train/search_frames``), and a result should add them and the run's own frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, get_args

import torch
from omegaconf import MISSING, DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, ValueOperator

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.keys import MASK
from torchrl_grpo.branching.lookahead import branch_returns
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.objectives.search_label_loss import SearchLabelLoss
from torchrl_grpo.training.algos.labelled_fit import LabelledFit, LabelledFitConfig
from torchrl_grpo.training.algos.registry import register_algorithm
from torchrl_grpo.training.choices import choice_enum
from torchrl_grpo.training.env_builder import env_overrides, steps_natively, tensor_covers
from torchrl_grpo.training.metrics import PhaseTimer
from torchrl_grpo.training.pretrained import load_run_policy

__all__ = ["SearchDistill", "SearchDistillConfig", "search_labels"]

#: Search distillation's name (``algo.name``).
SearchDistillVariant = Literal["search_distill"]

SearchDistillName = choice_enum(
    "SearchDistillName", SearchDistillVariant, "The search distillation.", module=__name__
)


@dataclass
class SearchDistillConfig(LabelledFitConfig):
    """``algo=search_distill``: the student fits the search over a run on its own states.

    The keys of :class:`~torchrl_grpo.training.algos.labelled_fit.LabelledFitConfig`,
    with one run: ``teachers`` holds the run whose greedy actions the search's branches
    follow (or ``teacher_runs`` that run's overrides, trained first into
    ``<run>/teachers/0``). ``horizon`` is the steps of a branch; ``regret_coeff`` weighs
    the expected regret beside the best set's cross-entropy, and ``crash_head_coeff``
    the crash head's fit to the branches' crash flags. ``start_from_run`` starts the
    student from the run's own weights: the next round of expert iteration, when the
    run is a search student itself.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.merge(OmegaConf.structured(SearchDistillConfig),
        ...                       {"name": "search_distill", "teachers": ["runs/a/last.pt"]})
        >>> cfg.horizon, cfg.regret_coeff, cfg.minibatch_size
        (8, 3.0, 256)
    """

    name: SearchDistillName = MISSING
    horizon: int = 8
    minibatch_size: int = 256
    max_minibatches: int | None = 64
    regret_coeff: float = 3.0


@torch.no_grad()
def search_labels(planner: LookaheadPolicy, rows: TensorDictBase) -> TensorDict:
    """Each row's observation, every action's branch return and whether its branch crashed.

    Args:
        planner: the search (its ``env`` a tensor simulator of ``n_actions x N`` worlds).
        rows: ``N`` states with their ``"observation"`` and ``"state"``.

    Returns:
        ``[N]`` rows of ``observation``, ``search_scores`` and ``search_crashed``.

    Example:
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> from torchrl_grpo.modules import make_scripted_policy
        >>> env = TensorHighwayEnv("highway-fast-v0", num_envs=2, return_state=True, seed=0)
        >>> planner = LookaheadPolicy(TensorHighwayEnv("highway-fast-v0", num_envs=10),
        ...                           make_scripted_policy("slower"), horizon=2)
        >>> labels = search_labels(planner, env.reset())
        >>> labels["search_scores"].shape, labels["search_crashed"].dtype
        (torch.Size([2, 5]), torch.bool)
    """
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        data = planner.branches(rows)
    mask = data.get(MASK)
    crashed = (data.get(("next", "crashed")).reshape(mask.shape) & mask).any(-1)
    return TensorDict(
        observation=rows.get("observation"),
        search_scores=branch_returns(data).float(),
        search_crashed=crashed,
        batch_size=rows.batch_size,
    )


@register_algorithm
class SearchDistill(LabelledFit):
    """DAgger with the lookahead search over a run as the expert, on the student's trunks.

    Example:
        >>> from torchrl_grpo.training import compose_config
        >>> cfg = compose_config(["algo=search_distill", "model=transformer"])  # no run given
        >>> try:
        ...     SearchDistill.check_config(cfg)
        ... except ValueError as err:
        ...     print(str(err)[:46])
        algo=search_distill searches over one run: alg
    """

    names = get_args(SearchDistillVariant)
    config_class = SearchDistillConfig
    config_name = "base_search_distill"
    trains_crash_head = True

    def __init__(self, cfg: DictConfig, policy: ProbabilisticActor, env: EnvBase) -> None:
        super().__init__(cfg, policy, env)
        (path,) = list(cfg.algo.teachers)
        self.tail = DeterministicActor(load_run_policy(str(path), cfg.env, env, "algo.teachers[0]"))
        self.tail.to(cfg.device)
        self.search_frames = 0
        self._planner: LookaheadPolicy | None = None

    @classmethod
    def check_config(cls, cfg: DictConfig) -> None:
        """Also refuses other than one run, no crash head, and a scenario off the tensor sim."""
        super().check_config(cfg)
        algo, model = cfg.algo, cfg.model
        runs = len(algo.teachers) + len(algo.get("teacher_runs") or [])
        if runs != 1:
            raise ValueError(
                "algo=search_distill searches over one run: algo.teachers=[runs/<run>/last.pt] "
                f"or one entry of algo.teacher_runs (got {runs} runs)"
            )
        if not model.get("crash_head", False):
            raise ValueError(
                "algo=search_distill fits the search's crash flags: it needs model.crash_head=true"
            )
        if not tensor_covers(cfg.env):
            raise ValueError(
                f"algo=search_distill searches on the tensor simulator, which does not cover "
                f"env.scenario={cfg.env.scenario} with env.config={env_overrides(cfg.env)}"
            )
        if algo.horizon < 1:
            raise ValueError(f"algo.horizon must be >= 1 (steps a branch), got {algo.horizon}")

    @classmethod
    def make_loss(
        cls, algo_cfg: DictConfig, policy: ProbabilisticActor, value: ValueOperator | None = None
    ) -> SearchLabelLoss:
        """The best set's cross-entropy, the expected regret and the crash head's fit."""
        head = next((m for m in policy.modules() if callable(getattr(m, "heads", None))), None)
        if head is None:
            raise ValueError("algo=search_distill needs model.crash_head=true")
        return SearchLabelLoss(
            head,
            regret_coeff=float(algo_cfg.regret_coeff),
            crash_coeff=float(algo_cfg.crash_head_coeff),
        )

    @classmethod
    def trunk_exploration(cls, algo_cfg: DictConfig) -> ExplorationType:
        """The student drives greedily, crash aversion included: the states it is tested on.

        Sampling visits states the greedy student never reaches and misses some it does
        (the search student sampling: 27.89 / 0.9% on the selection seeds; greedy:
        27.99 / 0.7%, docs/results.md).
        """
        return ExplorationType.DETERMINISTIC

    def planner(self, rows: int) -> LookaheadPolicy:
        """The search over the run, with a branch world for every action of ``rows`` states."""
        n_actions = int(self.env.action_spec.n)
        if self._planner is None or self._planner.env.batch_size[0] != n_actions * rows:
            env_cfg = self.cfg.env
            sim = TensorHighwayEnv(
                str(env_cfg.scenario),
                env_overrides(env_cfg),
                num_envs=n_actions * rows,
                device=self.device,
                seed=0,
                native=steps_natively(env_cfg, self.device),
            )
            self._planner = LookaheadPolicy(sim, self.tail, int(self.cfg.algo.horizon))
        return self._planner

    def update(self, batch: TensorDictBase, timer: PhaseTimer) -> dict[str, float]:
        """Label the batch's states by the search, keep them, then train on all kept."""
        rows = batch.reshape(-1)
        planner = self.planner(rows.shape[0])
        with timer("search"):
            before = planner.frames
            labels = search_labels(planner, rows)
            self.search_frames += planner.frames - before
        self._standardise(labels.get("observation"))
        stats = self.fit_kept(labels, timer)
        stats["train/search_frames"] = float(self.search_frames)
        return stats

    def _standardise(self, observation: torch.Tensor) -> None:
        # A network that standardises its inputs takes the statistics of the first
        # labelled states; a resumed or initialised one keeps those it was fitted with.
        for module in self.policy.modules():
            if callable(getattr(module, "standardise_from", None)) and not module.standardised:
                module.standardise_from(observation)

    def counters(self) -> dict[str, int]:
        """The search's branch steps so far: each evaluation's ``search_frames``."""
        return {"search_frames": self.search_frames}

    def state_dict(self) -> dict[str, Any]:  # noqa: D102
        return {**super().state_dict(), "search_frames": self.search_frames}

    def load_state_dict(self, checkpoint: dict[str, Any], source: str = "") -> None:  # noqa: D102
        super().load_state_dict(checkpoint, source)
        self.search_frames = int(checkpoint["search_frames"])
