"""K policy networks that act together and learn one by one.

A network fitted to rare states (the few roots where one action crashes and another
does not) fits them differently from one initialisation to the next: measured on the
training issue's recipe, five seeds crash in 2.4 to 5.7% of 1,000 episodes, and the
mean of their five logits in 2.1%. :class:`PolicyEnsemble` holds ``K`` networks of the
same architecture with their own initial weights. It acts with the mean of their
outputs; inside :meth:`PolicyEnsemble.acting` it is one member alone, which is how a
training loop gives each member the whole loss of its own outputs (the members are
fitted to the same data independently, rather than their mean fitted once, which would
be one wider network). Trained together in one run of the recipe (``model.ensemble=5``),
five members did not do what five runs did: 4.8% on seed 0, within that run's own range
(docs/results.md, "Where the crash rate moves"). :func:`member_halves` gives each member
its own half of the groups instead (``model.bagging``): three such members on the
recipe with branches of 4 steps crash in 3.2% over two seeds, one network in 3.7%.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from torch import nn

__all__ = ["PolicyEnsemble", "member_halves"]


class PolicyEnsemble(nn.Module):
    """The mean output of ``K`` networks, or one member's output inside :meth:`acting`.

    Args:
        members: the networks (at least 2), each mapping the same input to outputs of
            the same shape: logits, or a :class:`~torchrl_grpo.modules.CrashHead`'s.

    Example:
        >>> torch.manual_seed(0)
        <torch._C.Generator object at ...>
        >>> ensemble = PolicyEnsemble([nn.Linear(3, 2) for _ in range(3)])
        >>> x = torch.ones(4, 3)
        >>> mean = torch.stack([m(x) for m in ensemble.members]).mean(0)
        >>> torch.allclose(ensemble(x), mean)
        True
        >>> with ensemble.acting(1):
        ...     torch.equal(ensemble(x), ensemble.members[1](x))
        True
    """

    def __init__(self, members: list[nn.Module]) -> None:
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"an ensemble needs at least 2 members, got {len(members)}")
        self.members = nn.ModuleList(members)
        self.active: int | None = None

    def __len__(self) -> int:
        return len(self.members)

    @contextmanager
    def acting(self, member: int) -> Iterator[None]:
        """Within the block, the ensemble's outputs are ``members[member]``'s alone."""
        if not 0 <= member < len(self.members):
            raise IndexError(f"member {member} of an ensemble of {len(self.members)}")
        previous, self.active = self.active, member
        try:
            yield
        finally:
            self.active = previous

    def _combine(self, call: Callable[[nn.Module], torch.Tensor]) -> torch.Tensor:
        if self.active is not None:
            return call(self.members[self.active])
        return torch.stack([call(member) for member in self.members]).mean(0)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """The members' mean output (the active member's inside :meth:`acting`)."""
        return self._combine(lambda member: member(observation))

    def crash_logits(self, observation: torch.Tensor) -> torch.Tensor:
        """The members' mean crash logits, when the members are crash heads.

        Raises:
            TypeError: the members have no ``crash_logits``.
        """
        if not callable(getattr(self.members[0], "crash_logits", None)):
            raise TypeError(
                f"the ensemble's members ({type(self.members[0]).__name__}) have no "
                "crash_logits(observation): build them with model.crash_head=true"
            )
        return self._combine(lambda member: member.crash_logits(observation))


def _primes(count: int) -> list[int]:
    """The first ``count`` primes."""
    found: list[int] = []
    candidate = 2
    while len(found) < count:
        if all(candidate % p for p in found if p * p <= candidate):
            found.append(candidate)
        candidate += 1
    return found


def member_halves(group_id: torch.Tensor, members: int) -> torch.Tensor:
    """Which of ``members`` networks train on each row: a fixed half of the groups each.

    Five runs of a recipe crash in different states and their mean logits crash half as
    often; five members trained on the same groups do not (docs/results.md). Giving each
    member its own half of the groups (subsampling without replacement, "subagging")
    lets the members differ by their data inside one run. Member ``k`` keeps the groups
    with ``frac(group_id * a_k) < 1/2``, ``a_k`` the fractional part of the square root
    of the ``k``-th prime: a Weyl sequence per member, so consecutive group ids split
    evenly and the halves of two members are independent (the square roots of distinct
    primes are linearly independent over the rationals). The rows of one group (its
    branches, and its replays in later batches) fall in the same halves. A group in no
    member's half (one in ``2 ** members``) goes to member ``group_id mod members``, so
    none is dropped.

    Args:
        group_id: integer group ids, any shape.
        members: the ensemble's size (>= 1).

    Returns:
        A bool tensor ``[*group_id.shape, members]``: row ``i`` trains member ``k``
        where it is ``True``.

    Raises:
        ValueError: ``members < 1``.
        TypeError: the ids are not integers.

    Example:
        >>> halves = member_halves(torch.arange(10_000), 3)
        >>> halves.shape, [round(float(f), 3) for f in halves.float().mean(0)]
        (torch.Size([10000, 3]), [0.541, 0.542, 0.543])
        >>> bool(halves.any(-1).all())  # every group trains some member
        True
        >>> bool((member_halves(torch.tensor([7, 7]), 3) == halves[7]).all())
        True
    """
    if members < 1:
        raise ValueError(f"an ensemble has at least 1 member, got {members}")
    if group_id.dtype.is_floating_point or group_id.dtype == torch.bool:
        raise TypeError(f"group ids are integers, got {group_id.dtype}")
    ids = group_id.to(torch.float64).unsqueeze(-1)
    steps = torch.tensor([math.sqrt(p) % 1.0 for p in _primes(members)], dtype=torch.float64)
    halves = torch.frac(ids * steps) < 0.5
    orphan = ~halves.any(-1, keepdim=True)
    owner = torch.nn.functional.one_hot(group_id.long() % members, members).bool()
    return halves | (orphan & owner)
