"""The trunks' episode clock and greedy trunks (``algo=grpo_lab``), beyond the recipes'.

The recipe (``grpo_branch``) samples its trunks and takes decision points at every
episode step, its live trunks staggered over an episode. The lab bounds them:
``rollout.first_root_step`` starts a trunk's decision points at that step,
``rollout.full_horizon_roots`` ends trunks where a branch of ``H`` steps still fits
before the time limit; and ``algo.trunk=greedy`` has the policy act deterministically on
trunks, so that decision points are the states the evaluated policy visits. ``GRPOLab``
hands them to the core's collector builder (its ``trunk_schedule`` and
``trunk_exploration``). Measured in the lab notes; no recipe uses them.
"""

from __future__ import annotations

from typing import Any, Literal

from omegaconf import DictConfig
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.training.choices import choice_enum

__all__ = ["TrunkPolicyName", "check_trunk_bounds", "trunk_exploration", "trunk_schedule"]

#: How the policy acts on the trunks decision points are taken from (``algo.trunk``).
TrunkPolicy = Literal["sample", "greedy"]
TrunkPolicyName: Any = choice_enum(
    "TrunkPolicyName", TrunkPolicy, "How the policy acts on trunks.", module=__name__
)


def trunk_schedule(rollout: DictConfig, step_limit: int) -> tuple[int, int, int | None]:
    """The trunks' schedule (``stagger``, ``min_steps``, ``max_steps``), with their bounds.

    :func:`~torchrl_grpo.training.collect.trunk_schedule` with the lab's keys.

    ``rollout.first_root_step`` is the episode step of a trunk's first decision point.
    ``rollout.full_horizon_roots`` ends trunks at step ``T - H + 1`` of an episode of
    ``T = step_limit`` steps, so that every decision point's branches of ``H`` steps end
    before the time limit: the policy does not see the time, so a branch the limit cut
    short would teach it, in states like any other, that a crash after the cut costs
    nothing. ``rollout.stagger_trunks`` spreads the trunks over the steps where they
    have decision points.

    Raises:
        ValueError: no episode step is left for decision points.

    Example:
        >>> from omegaconf import OmegaConf
        >>> rollout = OmegaConf.create({"horizon": 8, "stagger_trunks": True,
        ...                             "full_horizon_roots": True, "first_root_step": 3})
        >>> trunk_schedule(rollout, 30)
        (20, 3, 23)
    """
    first = int(rollout.get("first_root_step", 0))
    last = step_limit
    if rollout.get("full_horizon_roots"):
        last = step_limit - int(rollout.horizon) + 1
    if not 0 <= first < last:
        raise ValueError(
            f"rollout.first_root_step={first} leaves no decision point in an episode of "
            f"{step_limit} steps (rollout.horizon={rollout.horizon}, "
            f"rollout.full_horizon_roots={rollout.get('full_horizon_roots')})"
        )
    stagger = last - first if rollout.get("stagger_trunks") else 0
    return stagger, first, last if rollout.get("full_horizon_roots") else None


def trunk_exploration(algo: DictConfig) -> ExplorationType:
    """How the policy acts on trunks (``algo.trunk``): samples, or acts greedily.

    Example:
        >>> from omegaconf import OmegaConf
        >>> greedy = trunk_exploration(OmegaConf.create({"trunk": "greedy"}))
        >>> greedy == ExplorationType.DETERMINISTIC
        True
    """
    if str(algo.get("trunk", "sample")) == "greedy":
        return ExplorationType.DETERMINISTIC
    return ExplorationType.RANDOM


def check_trunk_bounds(algo: DictConfig, rollout: DictConfig | None) -> None:
    """Refuses the trunks' bounds without trunks (``algo.roots`` other than ``trunk``).

    Raises:
        ValueError: naming the key and ``algo.roots=trunk``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_trunk_bounds(OmegaConf.create({"roots": "reset"}),
        ...                    OmegaConf.create({"first_root_step": 2}))
        Traceback (most recent call last):
        ...
        ValueError: rollout.first_root_step places decision points along trunks: it needs algo.roots=trunk, got algo.roots=reset
    """  # noqa: E501 - a doctest's expected output is one line
    keys = ("full_horizon_roots", "first_root_step")
    set_keys = [k for k in keys if rollout is not None and rollout.get(k)]
    if set_keys and str(algo.roots) != "trunk":
        raise ValueError(
            f"rollout.{set_keys[0]} places decision points along trunks: it needs "
            f"algo.roots=trunk, got algo.roots={algo.roots}"
        )
