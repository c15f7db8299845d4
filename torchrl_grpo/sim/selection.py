"""Which vehicles a substep computes a decision for: compacted, or all of them masked.

Most vehicles take no decision in a given substep (a MOBIL timer is due once a
second, few vehicles are changing lanes, few pairs are close enough to collide).
:func:`select` lists the (world, vehicle) pairs of a mask in one of two forms:

- compacted (``dense=False``): only the selected pairs, found with ``nonzero``. The
  least arithmetic, but a data-dependent shape (and, on a GPU, a host sync): the
  eager CPU path;
- dense (``dense=True``): every pair, with the mask kept as ``valid``. More
  arithmetic, but static shapes that ``torch.compile`` and CUDA graphs capture whole.

Both give the same values: results are written back with :func:`scatter`.

Example:
    >>> import torch
    >>> mask = torch.tensor([[False, True], [True, False]])
    >>> sel = select(mask, dense=False)
    >>> sel.rows.tolist(), sel.vehicle.tolist()
    ([0, 1], [1, 0])
    >>> scatter(torch.zeros(2, 2), sel, torch.tensor([5.0, 7.0])).tolist()
    [[0.0, 5.0], [7.0, 0.0]]
    >>> dense = select(mask, dense=True)
    >>> scatter(torch.zeros(2, 2), dense, torch.arange(4.0)).tolist()
    [[0.0, 1.0], [2.0, 0.0]]
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["Selection", "scatter", "select"]


class Selection(NamedTuple):
    """(world, vehicle) pairs of a ``[B, N]`` table.

    Attributes:
        rows: ``[Q]`` worlds.
        vehicle: ``[Q]`` vehicles.
        at: ``[Q]`` flat indices ``rows * N + vehicle``.
        valid: ``[Q]`` the mask (dense form), or ``None`` (compacted: all are selected).
    """

    rows: torch.Tensor
    vehicle: torch.Tensor
    at: torch.Tensor
    valid: torch.Tensor | None

    @property
    def empty(self) -> bool:
        """No pair is selected (known without a device sync only when compacted)."""
        return self.valid is None and self.at.numel() == 0


def select(mask: torch.Tensor, dense: bool) -> Selection:
    """The pairs where ``mask`` (``[B, N]``) is set.

    Args:
        mask: ``[B, N]`` bool.
        dense: every pair with the mask as ``valid``, instead of only the set ones.

    Returns:
        The :class:`Selection`.

    Example:
        >>> select(torch.tensor([[True, False]]), dense=True).valid.tolist()
        [True, False]
    """
    n = mask.shape[1]
    flat = mask.reshape(-1)
    if dense:
        at = torch.arange(flat.numel(), device=mask.device)
        valid = flat
    else:
        at = flat.nonzero().squeeze(-1)
        valid = None
    return Selection(at // n, at % n, at, valid)


def scatter(table: torch.Tensor, sel: Selection, values: torch.Tensor) -> torch.Tensor:
    """``table`` with ``values`` written at the selected pairs (a new tensor).

    Args:
        table: ``[B, N]``.
        sel: the pairs.
        values: ``[Q]``, one per pair of ``sel``.

    Returns:
        The new ``[B, N]`` table.

    Example:
        >>> sel = select(torch.tensor([[True, False]]), dense=False)
        >>> scatter(torch.zeros(1, 2), sel, torch.tensor([3.0])).tolist()
        [[3.0, 0.0]]
    """
    flat = table.reshape(-1)
    if sel.valid is None:
        return flat.index_copy(0, sel.at, values).view_as(table)
    return torch.where(sel.valid, values, flat).view_as(table)
