"""The probability that a branch cut by the horizon would survive the steps after it.

A horizon-H branch that ends alive is credited the steps left in its episode
(:class:`~torchrl_grpo.objectives.HorizonBootstrap`). When it ends in a trap (the ego
boxed in behind a vehicle it cannot brake for, a crash a few steps away) those steps
will not be driven: a target blind past the horizon scores the action that led there
as safe. A crash head already predicts, for every action, whether the next H steps
crash; asked at a branch's last state for the action the policy would take, it tells
the bootstrap how much of the tail to credit, for no extra simulated step.

The same probability can teach the head itself to look further
(:func:`crash_label`, ``algo.crash_label=bootstrap``; GRPO does so with
``algo.bootstrap=survival`` too, whatever ``algo.crash_label`` says): a branch the
horizon cut alive is labelled with the head's crash probability at its last state
instead of 0, so the head learns the probability of crashing before the episode ends, one horizon of
bootstrapping at a time (a temporal-difference target of the crash indicator).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import NestedKey, TensorDictBase
from torch import nn

from torchrl_grpo.objectives._keyed import KeyedModule

__all__ = ["CrashLabel", "TailSurvival", "crash_label"]

#: What a crash head learns of a branch: ``"branch"``, whether it crashed within the
#: horizon; ``"bootstrap"``, that, or where the horizon cut it alive, the head's own
#: crash probability at its last state (:func:`crash_label`). GRPO's survival bootstrap
#: labels as ``"bootstrap"`` does, whatever this says.
CrashLabel = Literal["branch", "bootstrap"]


class TailSurvival(KeyedModule):
    """Writes ``1 - p_crash(s_end, a*)`` on every step of each branch of a ``[..., T]`` batch.

    ``s_end`` is the observation after a branch's last valid step and ``a*`` the
    action the head's policy logits prefer there (the greedy policy's); ``p_crash`` is
    the head's crash probability of that action. Branches whose every step is masked
    get 1.

    Args:
        head: a module whose ``forward(observation)`` gives the policy's logits and
            ``crash_logits(observation)`` each action's crash logit, both
            ``[*batch, n_actions]`` (a :class:`~torchrl_grpo.modules.CrashHead`, or a
            :class:`~torchrl_grpo.modules.PolicyEnsemble` of them); used as it is.

    Keys (change them with :meth:`set_keys`): ``observation`` (``("next",
    "observation")``), ``mask`` (``"mask"``), written: ``survival`` (``"tail_survival"``,
    shaped like ``mask``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.modules import CrashHead
        >>> net = torch.nn.Linear(1, 4)  # 2 actions: 2 policy logits, 2 crash logits
        >>> with torch.no_grad():
        ...     _ = net.weight.zero_()
        ...     _ = net.bias.copy_(torch.tensor([1.0, 0.0, 0.0, 5.0]))  # prefers action 0
        >>> td = TensorDict({"mask": torch.tensor([[True, True], [True, False]]),
        ...                  ("next", "observation"): torch.zeros(2, 2, 1)}, batch_size=[2, 2])
        >>> out = TailSurvival(CrashHead(net, 2))(td)
        >>> out["tail_survival"]  # action 0's crash logit is 0: p = 1/2
        tensor([[0.5000, 0.5000],
                [0.5000, 0.5000]])
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read and written by :class:`TailSurvival`.

        Attributes:
            observation: the observation after each step, ``[..., T, *obs]``.
            mask: boolean, ``True`` on valid steps (a branch's steps come first).
            survival: written, the survival probability, on every step of the branch.
        """

        observation: NestedKey = ("next", "observation")
        mask: NestedKey = "mask"
        survival: NestedKey = "tail_survival"

    default_keys = _AcceptedKeys

    def __init__(self, head: nn.Module) -> None:
        if not callable(getattr(head, "crash_logits", None)):
            raise TypeError(
                f"{type(head).__name__} has no crash_logits(observation): build the policy "
                "with a crash head (model.crash_head=true)"
            )
        super().__init__()
        self.head = head

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        return [self.tensor_keys.observation, self.tensor_keys.mask]

    @property
    def out_keys(self) -> list[NestedKey]:  # noqa: D102
        return [self.tensor_keys.survival]

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes the survival probability into ``tensordict`` and returns it."""
        keys = self.tensor_keys
        mask = tensordict.get(keys.mask)
        shape = mask.shape
        steps = shape[-1]
        observation = tensordict.get(keys.observation)
        flat_obs = observation.reshape(-1, steps, *observation.shape[len(shape) :])
        lengths = mask.reshape(-1, steps).sum(-1)
        # Only the last valid step of each branch is asked: one forward per branch.
        last = flat_obs[torch.arange(flat_obs.shape[0]), (lengths - 1).clamp(min=0)]
        greedy = self.head(last).argmax(-1, keepdim=True)
        crash = torch.sigmoid(self.head.crash_logits(last).gather(-1, greedy)).squeeze(-1)
        survival = torch.where(lengths > 0, 1.0 - crash, torch.ones_like(crash))
        survival = survival.reshape(shape[:-1]).unsqueeze(-1).expand(shape)
        tensordict.set(keys.survival, survival.contiguous())
        return tensordict


def crash_label(crashed: torch.Tensor, cut: torch.Tensor, survival: torch.Tensor) -> torch.Tensor:
    """The probability that a branch's episode crashes: its bootstrapped crash label.

    1 where the branch crashed; ``1 - survival`` where the horizon cut it alive (the
    head's estimate for the rest of the episode from there, as :class:`TailSurvival`
    writes it); 0 where its episode ended without a crash. Arguments broadcast.

    Args:
        crashed: boolean, the branch crashed (the env terminated it).
        cut: boolean, the horizon ended the branch before its episode's end.
        survival: the probability of surviving the rest of the episode from the
            branch's last state, in ``[0, 1]``.

    Example:
        >>> crash_label(torch.tensor([True, False, False]), torch.tensor([False, True, False]),
        ...             torch.tensor([0.9, 0.75, 0.5]))
        tensor([1.0000, 0.2500, 0.0000])
    """
    zero = torch.zeros((), dtype=survival.dtype, device=survival.device)
    later = torch.where(cut & ~crashed, 1.0 - survival, zero)
    return torch.where(crashed, torch.ones_like(later), later)
