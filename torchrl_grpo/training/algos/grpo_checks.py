"""The relations between ``algo`` keys of GRPO that their types cannot express."""

from __future__ import annotations

from omegaconf import DictConfig

from torchrl_grpo.training.algos.enumerated import check_distill
from torchrl_grpo.training.algos.registry import with_fixed_settings

__all__ = ["check_grpo_config", "check_crash_head_needed"]


def check_grpo_config(cfg: DictConfig) -> None:
    """Refuse GRPO settings that contradict each other: greedy tails, replay, Ray.

    Raises:
        ValueError: the message names the keys and what to set instead.

    Example:
        >>> from torchrl_grpo.training import compose_config
        >>> learner_tails = ["algo.tail_policy=learner", "algo.tail_learner_steps=0"]
        >>> cfg = compose_config(["algo.replay_groups=8", *learner_tails])
        >>> check_grpo_config(cfg)
        Traceback (most recent call last):
        ...
        ValueError: algo.replay_groups=8 replays old groups, which is sound only when their advantages do not depend on the policy that collected them: set algo.first_action=enumerate and a scripted algo.tail_policy (e.g. rule)
    """  # noqa: E501 - a doctest's expected output is one line
    cfg = with_fixed_settings(cfg)  # the checks read the settings the recipe fixes too
    algo = cfg.algo
    if algo.group_size < 2:
        raise ValueError(f"algo.group_size must be >= 2, got {algo.group_size}")
    explore = algo.explore_steps
    tail_policy = str(algo.tail_policy)
    if tail_policy != "learner" and explore is None:
        raise ValueError(
            f"algo.tail_policy={tail_policy} is the base policy of greedy-tail "
            "branches: set algo.explore_steps too (e.g. 1)"
        )
    learner_steps = algo.get("tail_learner_steps", 0)
    if learner_steps < 0 or (learner_steps > 0 and tail_policy == "learner"):
        raise ValueError(
            f"algo.tail_learner_steps={learner_steps}: must be >= 0, and > 0 only with a "
            "scripted algo.tail_policy (e.g. rule), which takes over after those steps"
        )
    rollout = cfg.get("rollout")
    if rollout is not None and rollout.get("stagger_trunks") and str(algo.roots) != "trunk":
        raise ValueError(
            "rollout.stagger_trunks places decision points along trunks: it needs "
            f"algo.roots=trunk, got algo.roots={algo.roots}"
        )
    replay = algo.replay_groups
    if replay is not None:
        if replay < 1:
            raise ValueError(f"algo.replay_groups must be >= 1, got {replay}")
        if str(algo.first_action) != "enumerate" or tail_policy == "learner":
            raise ValueError(
                f"algo.replay_groups={replay} replays old groups, which is sound only when "
                "their advantages do not depend on the policy that collected them: set "
                "algo.first_action=enumerate and a scripted algo.tail_policy (e.g. rule)"
            )
    check_distill(algo)
    if str(algo.name) == "grpo_episode" and str(algo.group_fit_loss) != "regression":
        raise ValueError(
            f"algo.group_fit_loss={algo.group_fit_loss} fits each root's enumerated actions, "
            "which algo=grpo_episode's groups do not try: use algo=grpo_branch"
        )
    first_action = str(algo.first_action)
    if str(algo.action_weights) != "uniform" and first_action != "enumerate":
        raise ValueError(
            f"algo.action_weights={algo.action_weights} weighs enumerated first actions: set "
            "algo.first_action=enumerate (sampled actions are already drawn from the policy)"
        )
    if first_action != "sample" and explore is None:
        raise ValueError(
            f"algo.first_action={first_action} chooses the first action of "
            "greedy-tail branches: set algo.explore_steps too (e.g. 1)"
        )
    model = cfg.get("model")
    has_head = model is not None and bool(model.get("crash_head", False))
    check_crash_head_needed(algo, has_head)
    if has_head:
        if first_action != "enumerate" or explore != 1:
            raise ValueError(
                "model.crash_head learns whether each action, then the tail, crashes: set "
                "algo.first_action=enumerate and algo.explore_steps=1 (algo=grpo_branch)"
            )


def check_crash_head_needed(algo: DictConfig, has_head: bool) -> None:
    """Refuse ``algo.bootstrap=survival`` or ``algo.crash_label=bootstrap`` without a head.

    Both ask the crash head how likely a branch's last state is to crash next.

    Raises:
        ValueError: naming the option and ``model.crash_head=true``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_crash_head_needed(OmegaConf.create({"bootstrap": "survival"}), False)
        Traceback (most recent call last):
        ...
        ValueError: algo.bootstrap=survival asks the crash head how likely a branch's last state is to crash next: set model.crash_head=true
    """  # noqa: E501 - a doctest's expected output is one line
    if has_head:
        return
    for key, value in (("bootstrap", "survival"), ("crash_label", "bootstrap")):
        if str(algo.get(key, "")) == value:
            raise ValueError(
                f"algo.{key}={value} asks the crash head how likely a branch's last state "
                "is to crash next: set model.crash_head=true"
            )
