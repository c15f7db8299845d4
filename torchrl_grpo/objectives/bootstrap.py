"""The horizon bootstrap: the reward a branch cut by the horizon would still have earned.

Critic-free, for batches of branches laid out ``[..., T]`` (time last), as
:func:`~torchrl_grpo.branching.branch_rollout` and the group collectors write them. It
runs before the group-relative advantage, which then reads the training reward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import NestedKey, TensorDictBase

from torchrl_grpo.objectives._keyed import KeyedModule

__all__ = ["BootstrapMode", "HorizonBootstrap"]

#: ``"batch_mean"``: credit truncated branches with the batch's mean reward per step for
#: the episode steps left; ``"survival"``: the same, times each branch's probability of
#: surviving past its horizon (:class:`~torchrl_grpo.objectives.survival.TailSurvival`);
#: ``"none"``: the training reward is the env's reward.
BootstrapMode = Literal["none", "batch_mean", "survival"]


class HorizonBootstrap(KeyedModule):
    """Writes the training reward: the env's, plus a tail for branches cut by the horizon.

    A branch truncated by the horizon would go on collecting reward until its episode
    ends; a branch that the env ended (a crash: ``terminated``) would not. Without a
    critic, the tail is estimated as the batch's mean reward per valid step times the
    episode steps left, ``step_limit - (root_step + length)`` (at least 0), and added to
    the reward of the branch's last valid step. It is the same for every surviving
    branch of a group, so within the group it is the return a crash forfeits: without
    it, a crash late in a branch costs almost nothing and a policy learns to speed and
    crash. The env's reward is left untouched.

    Args:
        step_limit: the episode length in steps (e.g. a highway-env scenario's
            ``duration`` times its ``policy_frequency``).
        mode: ``"batch_mean"`` (the tail above), ``"survival"`` (that tail times the
            ``survival`` key at the branch's last step: the probability that the policy
            would not crash soon after the horizon, so that a branch that ends in a trap
            is not credited the steps it would not drive; written by
            :class:`~torchrl_grpo.objectives.survival.TailSurvival`), or ``"none"`` (the training
            reward is a copy of the env's).
        termination_penalty: subtracted from the training reward of a step where the
            env ended the episode (in highway-env a crash, or leaving the road with
            ``offroad_terminal``): shaping that makes a crash cost more than the reward
            it forfeits. ``0`` (the default) adds nothing.

    Keys (change them with :meth:`set_keys`): ``reward`` (``("next", "reward")``),
    ``terminated`` (``("next", "terminated")``), ``mask`` (``"mask"``: valid steps),
    ``root_step`` (``"root_step"``: the episode step of the branch's root), ``survival``
    (``"tail_survival"``, read with ``mode="survival"`` only), written:
    ``train_reward`` (``("next", "train_reward")``) and ``bootstrap`` (``"bootstrap"``:
    what was added to each step's reward, shaped like the reward).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.objectives import HorizonBootstrap
        >>> # Two branches of 3 steps from a root at episode step 4, in a 10-step episode:
        >>> # the first survives the horizon, the second crashes at its second step.
        >>> reward = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0]])
        >>> terminated = torch.tensor([[False, False, False], [False, True, False]])
        >>> td = TensorDict(
        ...     {
        ...         "mask": torch.tensor([[True, True, True], [True, True, False]]),
        ...         "root_step": torch.full((2, 3), 4),
        ...         ("next", "reward"): reward.unsqueeze(-1),
        ...         ("next", "terminated"): terminated.unsqueeze(-1),
        ...     },
        ...     batch_size=[2, 3],
        ... )
        >>> out = HorizonBootstrap(step_limit=10)(td)
        >>> out["next", "train_reward"].squeeze(-1)  # mean reward 0.8 x (10 - 7) steps left
        tensor([[1.0000, 1.0000, 3.4000],
                [1.0000, 0.0000, 0.0000]])
        >>> out["bootstrap"].sum((-2, -1))  # the tail of each branch
        tensor([2.4000, 0.0000])
        >>> out = HorizonBootstrap(step_limit=10, termination_penalty=5.0)(td)
        >>> out["next", "train_reward"].squeeze(-1)[1]  # the crash costs 5 more
        tensor([ 1., -5.,  0.])
        >>> td["tail_survival"] = torch.tensor([[0.5, 0.5, 0.25], [1.0, 1.0, 1.0]])
        >>> out = HorizonBootstrap(step_limit=10, mode="survival")(td)
        >>> out["bootstrap"].sum((-2, -1))  # 2.4 x 0.25, read at the first one's last step
        tensor([0.6000, 0.0000])
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read and written by :class:`HorizonBootstrap`.

        Attributes:
            reward: per-step reward, shape ``[..., T]`` or ``[..., T, 1]``.
            terminated: whether the env ended the episode at that step.
            mask: boolean, ``True`` on valid steps (a branch's steps come first).
            root_step: episode step of the branch's root, on every step.
            survival: with ``mode="survival"``, the probability of surviving past the
                horizon after each step, shaped like ``mask``; read at the last valid one.
            train_reward: written, the reward plus the tail (shaped like ``reward``).
            bootstrap: written, the tail added to each step (shaped like ``reward``).
        """

        reward: NestedKey = ("next", "reward")
        terminated: NestedKey = ("next", "terminated")
        mask: NestedKey = "mask"
        root_step: NestedKey = "root_step"
        survival: NestedKey = "tail_survival"
        train_reward: NestedKey = ("next", "train_reward")
        bootstrap: NestedKey = "bootstrap"

    default_keys = _AcceptedKeys

    def __init__(
        self, step_limit: int, mode: BootstrapMode = "batch_mean", termination_penalty: float = 0.0
    ) -> None:
        super().__init__()
        if not math.isfinite(termination_penalty) or termination_penalty < 0:
            raise ValueError(
                f"termination_penalty must be a finite number >= 0, got {termination_penalty}."
            )
        self.termination_penalty = float(termination_penalty)
        if mode not in ("none", "batch_mean", "survival"):
            raise ValueError(f"mode must be 'none', 'batch_mean' or 'survival', got {mode!r}.")
        if step_limit < 1:
            raise ValueError(f"step_limit must be >= 1, got {step_limit}.")
        self.step_limit = int(step_limit)
        self.mode = mode

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        k = self.tensor_keys
        survival = [k.survival] if self.mode == "survival" else []
        return [k.reward, k.terminated, k.mask, k.root_step, *survival]

    @property
    def out_keys(self) -> list[NestedKey]:  # noqa: D102
        return [self.tensor_keys.train_reward, self.tensor_keys.bootstrap]

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes the training reward and the tail into ``tensordict`` and returns it."""
        keys = self.tensor_keys
        reward = tensordict.get(keys.reward)
        mask = tensordict.get(keys.mask)
        shape = mask.shape
        train = reward.clone()
        bonus = torch.zeros_like(reward)
        if self.mode != "none" and bool(mask.any()):
            rate = float(reward.reshape(shape)[mask].mean())
            last = (mask.sum(-1) - 1).clamp(min=0).unsqueeze(-1)
            tail = rate * self.steps_left(tensordict)
            if self.mode == "survival":
                tail = tail * self._survival(tensordict, shape).gather(-1, last).squeeze(-1)
            tail = tail.unsqueeze(-1)
            train.view(shape).scatter_add_(-1, last, tail.to(train.dtype))
            bonus.view(shape).scatter_(-1, last, tail.to(bonus.dtype))
        if self.termination_penalty and bool(mask.any()):
            ended = tensordict.get(keys.terminated).reshape(shape) & mask
            penalty = (self.termination_penalty * ended).to(train.dtype)
            train.view(shape).sub_(penalty)
            bonus.view(shape).sub_(penalty.to(bonus.dtype))
        tensordict.set(keys.train_reward, train)
        tensordict.set(keys.bootstrap, bonus)
        return tensordict

    def steps_left(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``[...]``: the episode steps each branch's horizon cut off (``mask`` without ``T``).

        ``step_limit - (root_step + length)``, at least 0; 0 for a branch the env ended
        (``terminated`` at its last valid step) and for one without a valid step. It is
        what the tail is credited for, and > 0 exactly where the horizon cut a branch
        alive before its episode's end.
        """
        keys = self.tensor_keys
        mask = tensordict.get(keys.mask)
        lengths = mask.sum(-1)
        last = (lengths - 1).clamp(min=0).unsqueeze(-1)
        terminated = tensordict.get(keys.terminated).reshape(mask.shape)
        ended_by_env = terminated.gather(-1, last).squeeze(-1)
        step_end = tensordict.get(keys.root_step).reshape(mask.shape)[..., 0] + lengths
        left = (self.step_limit - step_end).clamp(min=0)
        return left * (~ended_by_env & (lengths > 0))

    def _survival(self, tensordict: TensorDictBase, shape: torch.Size) -> torch.Tensor:
        key = self.tensor_keys.survival
        if key not in tensordict.keys(include_nested=True):
            raise KeyError(
                f"HorizonBootstrap(mode='survival') reads {key!r}, which the tensordict "
                "lacks: run a TailSurvival on it first"
            )
        survival = tensordict.get(key).reshape(shape).float()
        if bool(((survival < 0) | (survival > 1) | survival.isnan()).any()):
            raise ValueError(f"{key!r} must hold probabilities in [0, 1]")
        return survival

    def extra_repr(self) -> str:  # noqa: D102
        return (
            f"step_limit={self.step_limit}, mode={self.mode!r}, "
            f"termination_penalty={self.termination_penalty}"
        )
