"""reset_world draws only the masked rows, and each row the same as when all rows reset."""

import pytest
import torch
from sim_helpers import fresh_world

from torchrl_grpo.sim import reset_world


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_partial_reset_draws_each_row_as_a_full_one(fast_params, dtype):
    # Worlds mid-episode (advanced counters, moved vehicles), so that a reset row differs.
    world = fresh_world(fast_params, 6, dtype, seed=4)
    world = world._replace(
        vehicles=world.vehicles._replace(x=world.vehicles.x + 7.0),
        time=world.time + 3.0,
        steps=world.steps + 15,
        rng_counter=world.rng_counter + 2,
    )
    mask = torch.tensor([False, True, False, False, True, True])
    every = reset_world(world, torch.ones(6, dtype=torch.bool), fast_params)
    partial = reset_world(world, mask, fast_params)
    for name, new, old, full in zip(world.vehicles._fields, partial.vehicles, world.vehicles,
                                    every.vehicles, strict=True):  # fmt: skip
        assert new.dtype == old.dtype, name
        assert torch.equal(new[mask], full[mask]), name
        assert torch.equal(new[~mask], old[~mask]), name
    for name in ("speed_index", "time", "steps", "rng_counter"):
        new, old, full = (getattr(w, name) for w in (partial, world, every))
        assert torch.equal(new[mask], full[mask]) and torch.equal(new[~mask], old[~mask]), name
    assert partial.time[mask].eq(0).all() and partial.steps[mask].eq(0).all()
    # Nothing to reset: the same world back.
    none = reset_world(world, torch.zeros(6, dtype=torch.bool), fast_params)
    assert all(torch.equal(a, b) for a, b in zip(none.vehicles, world.vehicles, strict=True))
