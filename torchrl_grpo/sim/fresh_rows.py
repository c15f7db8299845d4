"""Fresh worlds put in place: a batch with some of its rows replaced by new episodes.

The resets of merge-v0 and roundabout-v0 build only the rows that reset (a few of a
batch each step) and put them in place with this, so that a reset costs what its rows
cost, not the batch.

Example:
    >>> import torch
    >>> from torchrl_grpo.sim.state import empty_world
    >>> world = empty_world(3, 2, torch.float64)
    >>> fresh = empty_world(1, 2, torch.float64)
    >>> fresh = fresh._replace(vehicles=fresh.vehicles._replace(x=torch.ones(1, 2)))
    >>> put_rows(world, torch.tensor([1]), fresh.vehicles, torch.tensor([2])).vehicles.x
    tensor([[0., 0.],
            [1., 1.],
            [0., 0.]], dtype=torch.float64)
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim.state import Vehicles, World

__all__ = ["put_rows"]


def put_rows(
    world: World, rows: torch.Tensor, vehicles: Vehicles, speed_index: torch.Tensor, **fields
) -> World:
    """``world`` with ``rows`` (indices) started afresh: time and steps 0.

    Args:
        world: B worlds.
        rows: ``[K]`` int64 indices of the rows to replace.
        vehicles: their ``[K, N]`` vehicle tables.
        speed_index: their ``[K]`` ego speed indices.
        **fields: any other :class:`~torchrl_grpo.sim.state.World` field's ``K`` rows
            (``route``, ``route_head``).

    Returns:
        The new worlds; the other rows are ``world``'s.
    """

    def put(old: torch.Tensor, new: torch.Tensor | float) -> torch.Tensor:
        return old.index_put((rows,), torch.as_tensor(new, dtype=old.dtype, device=old.device))

    table = Vehicles(*(put(old, new) for old, new in zip(world.vehicles, vehicles, strict=True)))
    changed = {name: put(getattr(world, name), new) for name, new in fields.items()}
    return world._replace(
        vehicles=table,
        speed_index=put(world.speed_index, speed_index),
        time=put(world.time, 0.0),
        steps=put(world.steps, 0),
        **changed,
    )
