"""The averaged policy a run evaluates and saves (``optim.ema_decay``).

The greedy policy of an on-policy learner moves from update to update: its crash rate
can swing between evaluations one iteration apart. An exponential moving average of
the parameters (Polyak averaging) is a policy that moves slowly, without slowing the
learner: the updates still train the live policy, and the average only follows it.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn

__all__ = ["PolicyAverage"]


class PolicyAverage:
    """An exponential moving average of ``policy``'s parameters, updated once per iteration.

    The ``n``-th :meth:`update` moves each averaged parameter towards the live one by
    ``max(1 - decay, 1 / n)``: the first copies it, the next ones keep the exact mean of
    the policies so far until ``n`` reaches ``1 / (1 - decay)``, after which older
    policies fade by ``decay`` per update. Buffers are copied, not averaged.

    Args:
        policy: the live policy (trained by the optimiser; read, never written).
        decay: the weight of the average at each update, ``0 <= decay < 1`` (0: the
            average is the live policy).

    Example:
        >>> import torch
        >>> net = torch.nn.Linear(1, 1, bias=False)
        >>> average = PolicyAverage(net, decay=0.5)
        >>> for w in (4.0, 2.0, 0.0):
        ...     _ = net.weight.data.fill_(w)
        ...     average.update()
        >>> average.count, float(average.module.weight)  # 4, then (4+2)/2, then (3+0)/2
        (3, 1.5)
    """

    def __init__(self, policy: nn.Module, decay: float) -> None:
        if not 0 <= decay < 1:
            raise ValueError(f"optim.ema_decay must be in [0, 1), got {decay}")
        self.policy = policy
        self.decay = float(decay)
        self.module = copy.deepcopy(policy)
        self.module.requires_grad_(False)
        self.count = 0

    @torch.no_grad()
    def update(self) -> None:
        """Move the average towards the live policy (once per training iteration)."""
        self.count += 1
        weight = max(1.0 - self.decay, 1.0 / self.count)
        for average, live in zip(self.module.parameters(), self.policy.parameters(), strict=True):
            average.lerp_(live, weight)
        for average, live in zip(self.module.buffers(), self.policy.buffers(), strict=True):
            average.copy_(live)

    def state_dict(self) -> dict[str, Any]:
        """The live policy's parameters and the update count (the average is the policy's)."""
        return {"train_policy": self.policy.state_dict(), "count": self.count}

    def load_state_dict(self, average: dict[str, Any], state: dict[str, Any] | None) -> None:
        """Restore from a checkpoint's ``policy`` (``average``) and ``policy_average`` (``state``).

        Without ``state`` (a checkpoint written without averaging), the live policy and
        the average both start from ``average`` and the count from 0.
        """
        self.module.load_state_dict(average)
        if state is None:
            self.policy.load_state_dict(average)
            self.count = 0
        else:
            self.policy.load_state_dict(state["train_policy"])
            self.count = int(state["count"])
