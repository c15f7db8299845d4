"""Driving features read from the simulator's vehicle table, hidden fields included.

A diagnostic of ``bench_offline_fit.py --privileged``: what a network could reach if it
saw everything the planner's branches depend on. For the ego's lane and the lanes beside
it, the two nearest vehicles ahead and the nearest behind, each with its gap, closing
speed, and what no Kinematics observation shows: how far its speed is from its target
speed, its acceleration, its lane-change intent (target lane minus lane) and its
offset from its lane's centre; and the ego's own speed, target speed, acceleration,
heading and lateral offset. Vehicles are taken from the whole table (every vehicle,
ahead and behind, at any distance).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

LANE_WIDTH, LENGTH, FAR = 4.0, 5.0, 100.0
FIELDS = ("x", "y", "heading", "speed", "target_speed", "acceleration", "lane", "target_lane")


def privileged_features(table: dict) -> torch.Tensor:
    """``[N, 3 + 4 + 3 * (1 + 3 * 6)]`` features of ``[N, V]`` vehicle tables (row 0: ego)."""
    v = {k: table[k].float() for k in FIELDS}
    present = table["present"].bool()
    ego = {k: t[:, :1] for k, t in v.items()}
    dx = v["x"] - ego["x"]
    others = present.clone()
    others[:, 0] = False
    rel_lane = v["lane"] - ego["lane"]
    rel_target = v["target_lane"] - ego["lane"]
    centre = v["lane"] * LANE_WIDTH
    feats = [
        (ego["speed"][:, 0] - 25.0) / 5.0,
        (ego["target_speed"][:, 0] - 25.0) / 5.0,
        ego["acceleration"][:, 0] / 5.0,
        ego["heading"][:, 0] * 10.0,
        (ego["y"][:, 0] - centre[:, 0]) / 2.0,
        (ego["target_lane"][:, 0] - ego["lane"][:, 0]),
        ego["lane"][:, 0],
    ]
    n_lanes = 3
    for offset in (-1, 0, 1):
        lane = ego["lane"][:, 0] + offset
        feats.append(((lane >= 0) & (lane < n_lanes)).float())
        member = others & ((rel_lane == offset) | (rel_target == offset))
        for ahead, rank in ((True, 0), (True, 1), (False, 0)):
            side = dx > 0 if ahead else dx <= 0
            dist = torch.where(member & side, dx.abs(), torch.full_like(dx, float("inf")))
            ordered, idx = dist.sort(-1)
            d, i = ordered[:, rank], idx[:, rank : rank + 1]
            found = torch.isfinite(d)

            def pick(t: torch.Tensor, i=i, found=found, d=d) -> torch.Tensor:
                return torch.where(found, t.gather(1, i).squeeze(1), torch.zeros_like(d))

            dvx = pick(v["speed"] * torch.cos(v["heading"])) - ego["speed"][:, 0]
            closing = -dvx if ahead else dvx
            gap = torch.where(found, (d - LENGTH).clamp(0, FAR), torch.full_like(d, FAR))
            feats += [
                gap / 50.0,
                closing / 10.0,
                pick(v["target_speed"] - v["speed"]) / 5.0,
                pick(v["acceleration"]) / 5.0,
                pick(v["target_lane"] - v["lane"]),
                pick(v["y"] - centre) / 2.0,
            ]
    return torch.stack(feats, -1)


class PrivilegedPolicy(TensorDictModuleBase):
    """Greedy actions of ``net`` over :func:`privileged_features` of the input's state."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net
        self.in_keys = [("state", "vehicles")]
        self.out_keys = ["action"]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        table = td.get(("state", "vehicles"))
        flat = {k: table.get(k).reshape(-1, table.shape[-1]) for k in (*FIELDS, "present")}
        logits = self.net(privileged_features(flat))
        return td.set("action", logits.argmax(-1).reshape(td.batch_size))
