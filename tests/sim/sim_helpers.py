"""Worlds for the simulator's tests."""

import torch

from torchrl_grpo.sim import empty_world, reset_world, seed_keys


def fresh_world(params, batch: int, dtype=torch.float64, seed: int = 0):
    """B fresh worlds drawn by the simulator's own reset."""
    world = empty_world(batch, params.num_vehicles, dtype)
    world = world._replace(rng_key=seed_keys(torch.arange(batch), seed))
    return reset_world(world, torch.ones(batch, dtype=torch.bool), params)
