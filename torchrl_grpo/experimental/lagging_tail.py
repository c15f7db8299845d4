"""A lagging tail policy (``algo=grpo_lab algo.tail_sync_batches=k``).

By default the learner's greedy tails (and trunks) follow the current policy, so the
policy the groups score changes after every batch. With ``k``, they follow a frozen copy
of the policy refreshed every ``k`` batches: ``k`` batches of groups score one fixed
policy, as approximate policy iteration evaluates a policy before it improves on it. The
copy is part of the checkpoint (the core's GRPO saves its tail policy's parameters).
Measured in the lab notes; no recipe uses it.
"""

from __future__ import annotations

import copy

from omegaconf import DictConfig
from torch import nn

__all__ = ["check_tail_sync", "lagging_copy"]


def lagging_copy(policy: nn.Module) -> nn.Module:
    """A frozen copy of ``policy``, the actor of greedy tails until the next sync.

    Example:
        >>> tail = lagging_copy(nn.Linear(2, 1))
        >>> [p.requires_grad for p in tail.parameters()]
        [False, False]
    """
    tail = copy.deepcopy(policy)
    tail.requires_grad_(False)
    return tail


def check_tail_sync(algo: DictConfig) -> None:
    """Refuses an ``algo.tail_sync_batches`` that no greedy tail of the learner follows.

    Raises:
        ValueError: ``k < 1``, no greedy-tail branches (``algo.explore_steps=null``), or
            a scripted ``algo.tail_policy`` (the copy is the learner's).

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_tail_sync(OmegaConf.create({"tail_sync_batches": 2, "explore_steps": 1,
        ...                                   "tail_policy": "rule"}))
        Traceback (most recent call last):
        ...
        ValueError: algo.tail_policy=rule is the base policy of greedy-tail branches: leave algo.tail_sync_batches null (it refreshes a learner's copy)
    """  # noqa: E501 - a doctest's expected output is one line
    tail_sync = algo.get("tail_sync_batches")
    if tail_sync is None:
        return
    if tail_sync < 1 or algo.explore_steps is None:
        raise ValueError(
            f"algo.tail_sync_batches={tail_sync}: must be >= 1, and applies to "
            "greedy-tail branches only (set algo.explore_steps too)"
        )
    if str(algo.tail_policy) != "learner":
        raise ValueError(
            f"algo.tail_policy={algo.tail_policy} is the base policy of greedy-tail "
            "branches: leave algo.tail_sync_batches null (it refreshes a learner's copy)"
        )
