"""Helpers shared by the modules tests: hand-built Kinematics observations, a counted network.

A plain module rather than conftest.py, whose name other test folders share.
"""

from __future__ import annotations

import torch
from torch import nn

from torchrl_grpo.modules import KinematicsLayout

LAYOUT = KinematicsLayout()  # highway-fast-v0: default Kinematics observation, 3 lanes
LANE = LAYOUT.lane_width


def scene(
    lane: int, speed: float, others: list[tuple[float, int, float]] = (), rows: int = 5
) -> torch.Tensor:
    """Observation for an ego in ``lane`` at ``speed``; others are (dx m, lane offset, dvx)."""
    cols = {f: torch.zeros(rows) for f in LAYOUT.features}
    cols["presence"][0] = 1.0
    cols["x"][0] = 150.0
    cols["y"][0] = lane * LANE
    cols["vx"][0] = speed
    for i, (dx, dlane, dvx) in enumerate(others, start=1):
        cols["presence"][i] = 1.0
        cols["x"][i] = dx
        cols["y"][i] = dlane * LANE
        cols["vx"][i] = dvx
    return LAYOUT.encode(cols)


class Counted(nn.Module):
    """A linear layer that counts how often it really runs."""

    def __init__(self, n_in: int, n_out: int) -> None:
        super().__init__()
        self.linear = nn.Linear(n_in, n_out)
        self.runs = 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        self.runs += 1
        return self.linear(x)
