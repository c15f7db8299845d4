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

With a ``margin``, the policy acting greedily (inside :func:`acting_greedily`, which
:class:`~torchrl_grpo.modules.DeterministicActor` enters: every evaluation here) never
takes an action whose probability exceeds the ``fallback`` action's (SLOWER) by more
than the margin. The head scores "this action, then the branches'
tail policy"; when that tail is always-``fallback``, a policy that never plays an action
riskier than ``fallback`` by more than ``margin`` crashes at most ``margin`` more often
per step than always-``fallback`` from the same states (the performance-difference
lemma, with the crash as the cost), whatever its logits prefer. Sampling and the losses,
which train, see every action: barred while training, the policy stops in states where
the head is unsure, and the head never learns the states it would have reached
(docs/lab/scenarios.md). Not the exploration type: TorchRL's losses run under
``DETERMINISTIC`` too.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import torch
from torch import nn

__all__ = ["BARRED", "CrashHead", "acting_greedily"]

#: How far below the lowest allowed logit a barred action's logit is put (``e^-30``: its
#: probability is nil, and its log-probability stays finite for the losses).
BARRED = 30.0

_GREEDY: ContextVar[bool] = ContextVar("acting_greedily", default=False)


@contextmanager
def acting_greedily() -> Iterator[None]:
    """Within it, a :class:`CrashHead` with a margin bars the actions riskier than SLOWER.

    Example:
        >>> with acting_greedily():
        ...     _GREEDY.get()
        True
        >>> _GREEDY.get()
        False
    """
    token = _GREEDY.set(True)
    try:
        yield
    finally:
        _GREEDY.reset(token)


class CrashHead(nn.Module):
    """Split a network's ``2 n`` outputs into ``n`` policy logits and ``n`` crash logits.

    Args:
        net: maps the observation to ``[*batch, 2 * n_actions]``: the policy's logits,
            then the crash logits.
        n_actions: number of discrete actions.
        aversion: weight of ``log(1 - p_crash)`` added to each action's logit (>= 0; 0:
            the head is trained but does not act). The head's output is detached there:
            only its own loss trains it.
        margin: with a ``fallback``, how much more likely to crash than it an action may
            be and still be the greedy choice (in ``[0, 1]``; None: every action may be).
        fallback: the index of the action that is always allowed (SLOWER); needed with
            ``margin``.

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

        A margin bars the actions that the head finds riskier than the fallback from the
        greedy choice:

        >>> net = nn.Linear(1, 4)
        >>> with torch.no_grad():  # p_crash: sigmoid(-4) ~ 0.018 for action 0, 0.5 for 1
        ...     _ = net.weight.zero_(), net.bias.copy_(torch.tensor([0.0, 5.0, -4.0, 0.0]))
        >>> barred = CrashHead(net, 2, margin=0.1, fallback=0)
        >>> with acting_greedily():
        ...     barred(torch.zeros(1, 1)).detach()  # action 1: 30 below the lowest logit
        tensor([[  0., -30.]])
        >>> barred(torch.zeros(1, 1)).detach()  # sampling and the losses see every action
        tensor([[0., 5.]])
    """

    def __init__(
        self,
        net: nn.Module,
        n_actions: int,
        aversion: float = 0.0,
        margin: float | None = None,
        fallback: int | None = None,
    ) -> None:
        super().__init__()
        if not (aversion >= 0 and aversion < float("inf")):
            raise ValueError(f"aversion must be a finite number >= 0, got {aversion}")
        self.net = net
        self.n_actions = int(n_actions)
        self.aversion = float(aversion)
        self.set_margin(margin, fallback)

    def set_margin(self, margin: float | None, fallback: int | None = None) -> None:
        """Bar (or, with ``margin=None``, stop barring) the actions riskier than ``fallback``.

        Raises:
            ValueError: a margin outside ``[0, 1]``, or one without a valid fallback.
        """
        if margin is not None:
            if not (0 <= margin <= 1):
                raise ValueError(f"margin must be a probability in [0, 1], got {margin}")
            if fallback is None or not 0 <= fallback < self.n_actions:
                raise ValueError(
                    f"a margin needs the index of a fallback action in [0, {self.n_actions}), "
                    f"got {fallback}"
                )
        self.margin = None if margin is None else float(margin)
        self.fallback = fallback

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
        return self.acted(*self._split(observation))

    def acted(self, logits: torch.Tensor, crash: torch.Tensor) -> torch.Tensor:
        """The logits the policy acts on, from the network's own and the crash logits."""
        if self.aversion != 0:
            logits = logits + self.aversion * nn.functional.logsigmoid(-crash.detach())
        if self.margin is None or not _GREEDY.get():
            return logits
        floor = logits.detach().amin(-1, keepdim=True) - BARRED
        return torch.where(self._allowed(crash), logits, floor)

    def heads(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The network's own policy logits (no aversion, no bar) and the crash logits."""
        return self._split(observation)

    def crash_logits(self, observation: torch.Tensor) -> torch.Tensor:
        """The logit of each action's crash probability, ``[*batch, n_actions]``."""
        return self._split(observation)[1]

    def allowed(self, observation: torch.Tensor) -> torch.Tensor:
        """Which actions the margin lets the greedy choice take, ``[*batch, n_actions]``.

        Every action without a margin; otherwise those the head finds at most ``margin``
        likelier to crash than the fallback (the fallback always). Other heads' bars
        can be laid over a policy's with it.
        """
        crash = self.crash_logits(observation)
        if self.margin is None:
            return torch.ones_like(crash, dtype=torch.bool)
        return self._allowed(crash)

    def _allowed(self, crash: torch.Tensor) -> torch.Tensor:
        risk = torch.sigmoid(crash.detach())
        return risk <= risk[..., self.fallback : self.fallback + 1] + self.margin
