"""A crash head scored under the base policy alone (``algo=grpo_lab algo.crash_head_tail=true``).

With the learner's own tails (``algo.tail_learner_steps``), a group scores each action
followed by the learner, and so does the crash head: it learns "this action, then the
learner". The crash margin (``model.crash_margin``) compares an action with SLOWER
under that head, and SLOWER followed by the learner is not always-SLOWER: the bound of
the performance-difference lemma (at most ``margin`` more crashes per step than
always-SLOWER) holds only when the head's tail is the base policy itself
(docs/lab/scenarios.md, "At 2.4M frames").

With this key each group holds every action twice (``algo.group_size`` = 2 x the
actions): the first half's branches follow the learner for ``tail_learner_steps`` and
train the policy; the second half's follow ``algo.tail_policy`` right after the first
action (:class:`~torchrl_grpo.modules.GreedyTail`'s ``learner_branches``), and label the
crash head of the same root and action. The policy keeps learning from its own
continuation, and the head scores the states the learner visits under the base tail,
which brings the margin's bound back. The second half's steps are simulated, so they
count as frames.
"""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from torchrl_grpo.branching.keys import MASK
from torchrl_grpo.training.algos.enumerated import branch_crashed

__all__ = ["BASE_TAIL_CRASHED", "base_tail_crashes", "check_crash_head_tail"]

#: On the learner's half of the groups being updated: whether the branch of the same root
#: and first action that followed the base tail crashed (the crash head's label).
BASE_TAIL_CRASHED = "base_tail_crashed"


def check_crash_head_tail(algo: DictConfig, has_head: bool, n_actions: int | None) -> None:
    """Refuse ``algo.crash_head_tail`` where the groups cannot hold every action twice.

    Args:
        algo: the ``algo`` config.
        has_head: whether the model has a crash head (``model.crash_head``).
        n_actions: the env's number of actions (``None``: not known yet, not checked).

    Raises:
        ValueError: the message names the key to set.

    Example:
        >>> from omegaconf import OmegaConf
        >>> algo = OmegaConf.create({"crash_head_tail": True, "first_action": "enumerate",
        ...     "explore_steps": 1, "tail_policy": "slower", "tail_learner_steps": 10,
        ...     "group_size": 5, "bootstrap": "batch_mean", "crash_label": "branch"})
        >>> check_crash_head_tail(algo, True, 5)
        Traceback (most recent call last):
        ...
        ValueError: algo.crash_head_tail=true scores every action twice (after the learner, after the base tail): set algo.group_size=10, twice the 5 actions (got 5)
    """  # noqa: E501 - a doctest's expected output is one line
    if not algo.get("crash_head_tail", False):
        return
    name = "algo.crash_head_tail=true"
    if not has_head:
        raise ValueError(f"{name} labels the crash head: set model.crash_head=true")
    if str(algo.first_action) != "enumerate" or algo.explore_steps != 1:
        raise ValueError(
            f"{name} pairs the branches of one root by their enumerated first action: set "
            f"algo.first_action=enumerate and algo.explore_steps=1 (got "
            f"{algo.first_action} and {algo.explore_steps})"
        )
    if str(algo.tail_policy) == "learner" or int(algo.tail_learner_steps) < 1:
        raise ValueError(
            f"{name} scores the crash head under a scripted base tail while the policy "
            "learns from its own: set a scripted algo.tail_policy (e.g. slower) and "
            f"algo.tail_learner_steps >= 1 (got {algo.tail_policy} and "
            f"{algo.tail_learner_steps})"
        )
    if str(algo.bootstrap) == "survival" or str(algo.crash_label) != "branch":
        raise ValueError(
            f"{name} labels the head with the base tail's crashes: set "
            f"algo.crash_label=branch and no survival bootstrap (got algo.crash_label="
            f"{algo.crash_label}, algo.bootstrap={algo.bootstrap})"
        )
    if n_actions is not None and int(algo.group_size) != 2 * n_actions:
        raise ValueError(
            f"{name} scores every action twice (after the learner, after the base tail): "
            f"set algo.group_size={2 * n_actions}, twice the {n_actions} actions "
            f"(got {algo.group_size})"
        )


def base_tail_crashes(batch: TensorDictBase) -> tuple[TensorDictBase, torch.Tensor]:
    """Split ``[R, 2n, T]`` groups into the learner's half and its crash labels.

    Returns:
        ``(batch[:, :n], labels)``: the branches that followed the learner, and, on each
        of their steps, whether the branch of the same root and first action that
        followed the base tail crashed (``[R, n, T]``).

    Example:
        >>> from tensordict import TensorDict
        >>> terminated = torch.zeros(1, 4, 2, 1, dtype=torch.bool)
        >>> terminated[0, 3, 1] = True  # action 1 crashes under the base tail only
        >>> batch = TensorDict({MASK: torch.ones(1, 4, 2, dtype=torch.bool),
        ...                     ("next", "terminated"): terminated}, batch_size=[1, 4, 2])
        >>> learner, labels = base_tail_crashes(batch)
        >>> learner.batch_size, labels.tolist()
        (torch.Size([1, 2, 2]), [[[False, False], [True, True]]])
    """
    groups = batch.batch_size[1]
    if groups % 2:
        raise ValueError(f"groups of every action twice have an even size, got {groups}")
    half = groups // 2
    return batch[:, :half], branch_crashed(batch[:, half:], MASK)
