"""A second head beside the policy's logits: the probability that each action crashes.

A group whose branches each take a different first action from one root, then follow a
fixed policy, tells exactly which actions of that root end in a crash within the
horizon. :class:`CrashHead` gives the policy network a second output per action, the
logit of that probability, trained by a binary cross-entropy on those labels
(:class:`~torchrl_grpo.objectives.CrashHeadLoss`). Measured on the planner's labels
(``benchmarks/lab/bench_offline_fit.py``), the second task alone makes the network's
greedy choices crash less: binary labels give the features of a coming crash a gradient
of their own, where a regression of returns mixes them with small differences of speed.
With ``aversion > 0`` the probability also enters the policy: its logits become
``l_a + aversion * log(1 - p_a)``, so an action the head expects to crash is played
less, the more so the surer the head is.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["CrashHead"]


class CrashHead(nn.Module):
    """Split a network's ``2 n`` outputs into ``n`` policy logits and ``n`` crash logits.

    Args:
        net: maps the observation to ``[*batch, 2 * n_actions]``: the policy's logits,
            then the crash logits.
        n_actions: number of discrete actions.
        aversion: weight of ``log(1 - p_crash)`` added to each action's logit (>= 0; 0:
            the head is trained but does not act). The head's output is detached there:
            only its own loss trains it.

    Example:
        >>> net = nn.Linear(3, 4)
        >>> head = CrashHead(net, 2, aversion=2.0)
        >>> x = torch.zeros(1, 3)
        >>> out = net(x)
        >>> survive = nn.functional.logsigmoid(-out[:, 2:])
        >>> torch.allclose(head(x), out[:, :2] + 2.0 * survive)
        True
        >>> head.crash_logits(x).shape
        torch.Size([1, 2])
    """

    def __init__(self, net: nn.Module, n_actions: int, aversion: float = 0.0) -> None:
        super().__init__()
        if not (aversion >= 0 and aversion < float("inf")):
            raise ValueError(f"aversion must be a finite number >= 0, got {aversion}")
        self.net = net
        self.n_actions = int(n_actions)
        self.aversion = float(aversion)

    def _split(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.net(observation)
        if out.shape[-1] != 2 * self.n_actions:
            raise ValueError(
                f"CrashHead needs a network with 2 * n_actions = {2 * self.n_actions} "
                f"outputs, got {out.shape[-1]}"
            )
        return out[..., : self.n_actions], out[..., self.n_actions :]

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """The policy's logits ``[*batch, n_actions]``."""
        logits, crash = self._split(observation)
        if self.aversion == 0:
            return logits
        return logits + self.aversion * nn.functional.logsigmoid(-crash.detach())

    def crash_logits(self, observation: torch.Tensor) -> torch.Tensor:
        """The logit of each action's crash probability, ``[*batch, n_actions]``."""
        return self._split(observation)[1]
