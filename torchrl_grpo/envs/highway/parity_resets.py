"""Rung d of the parity ladder: fresh tensor worlds against highway-env's recorded statistics.

The reference files (``tests/data/highway_reference/<scenario>.json``) are written by
``scripts/highway_reference.py`` from highway-env runs; this module draws fresh worlds
with the tensor simulator's own reset and drives the same policies, then compares with
the two-sample tests of :mod:`.parity_stats`. Statistics are over the road's vehicles
(merge-v0's obstacle is no vehicle) and lane ids within each road, as the reference
records them.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from torchrl_grpo.envs.highway.parity_stats import chi2_counts, ks_2samp, proportions_z
from torchrl_grpo.envs.highway.tensor_env import TensorHighwayEnv
from torchrl_grpo.sim.intersection import road_order

__all__ = ["fresh_resets"]

Policy = Callable[[TensorDictBase], TensorDictBase]


def _initial_statistics(state: TensorDictBase, params) -> dict[str, torch.Tensor]:
    """Gaps between consecutive vehicles (road order), others' speeds, every lane's id.

    On intersection-v0 (one lane a road) a lane is its flat id, and only the present
    rows count, in road order (the ego after ``ego_rank`` others). Gaps and speeds are
    rounded to 6 decimals, as the reference stores them: intersection-v0's gaps hold
    point masses (cars spawned at the same place) that unrounded values of +-1e-14
    would split, and the Kolmogorov-Smirnov statistic would see the split.
    """
    if "ego_rank" in state.keys():
        return _present_statistics(state)
    n = getattr(params, "obstacle_row", params.num_vehicles)  # road.vehicles only
    x = state.get(("vehicles", "x"))[:, :n].double()
    lanes = state.get(("vehicles", "lane"))[:, :n]
    lane_id = getattr(params.road, "lane_id", None)
    if lane_id is not None:  # a lane graph: the id within its road, as lane_index[2]
        lanes = torch.tensor(lane_id, device=lanes.device)[lanes]
    return {
        "gaps": _rounded((x[:, 1:] - x[:, :-1]).flatten()),
        "speeds": _rounded(state.get(("vehicles", "speed"))[:, 1:n].double().flatten()),
        "lanes": lanes.flatten(),
    }


def _rounded(values: torch.Tensor) -> torch.Tensor:
    return torch.round(values, decimals=6)


def _present_statistics(state: TensorDictBase) -> dict[str, torch.Tensor]:
    present = state.get(("vehicles", "present"))
    order = road_order(state.get("ego_rank"), present.shape[1])
    x = state.get(("vehicles", "x")).double().gather(1, order)
    pairs = present.gather(1, order)[:, 1:] & present.gather(1, order)[:, :-1]
    others = present.clone()
    others[:, 0] = False
    return {
        "gaps": _rounded((x[:, 1:] - x[:, :-1])[pairs]),
        "speeds": _rounded(state.get(("vehicles", "speed")).double()[others]),
        "lanes": state.get(("vehicles", "lane"))[present],
    }


def fresh_resets(
    scenario: str,
    reference: dict,
    policies: dict[str, Policy],
    episodes: int = 1000,
    *,
    config: dict | None = None,
    seed: int = 0,
    decimals: int = 4,
    native: bool = False,
) -> list[dict]:
    """Rung d: fresh tensor worlds against highway-env's recorded statistics (no bridge).

    ``episodes`` worlds are drawn by the tensor simulator's own reset; each policy
    drives one episode in each. Returns and initial gaps and speeds are compared with
    two-sample Kolmogorov-Smirnov tests (returns rounded to ``decimals``: the always-
    SLOWER episodes tie), crash rates with a two-proportion z-test and lanes with a
    chi-square test.

    Args:
        scenario: the scenario the reference was recorded on.
        reference: ``tests/data/highway_reference/<scenario>.json``'s content.
        policies: the reference's policies by name (``idle``, ``slower``, ``random``, ``rule``).
        episodes: tensor episodes per policy.
        config: the config the reference was recorded with.
        seed: seeds the tensor worlds.
        decimals: rounding of returns before their test.
        native: step the tensor worlds in C++ (``TensorHighwayEnv(native=True)``).

    Returns:
        One row per comparison: ``{"what", "tensor", "highway", "statistic", "p"}``.
    """
    rows: list[dict] = []

    def row(what: str, mine: float, theirs: float, test: tuple[float, float]) -> None:
        rows.append(
            {"what": what, "tensor": mine, "highway": theirs, "statistic": test[0], "p": test[1]}
        )

    env = None
    for name, policy in policies.items():
        env = TensorHighwayEnv(
            scenario, config, num_envs=episodes, seed=seed, dtype=torch.float64, native=native
        )
        td = env.reset()
        if not rows:
            mine = _initial_statistics(td.get("state"), env.params)
            theirs = {
                k: torch.tensor([v for world in reference["initial"] for v in world[k]])
                for k in mine
            }
            for k in ("gaps", "speeds"):
                row(
                    f"initial {k}",
                    float(mine[k].mean()),
                    float(theirs[k].mean()),
                    ks_2samp(mine[k], theirs[k]),
                )
            lanes = int(max(int(t["lanes"].max()) for t in (mine, theirs))) + 1
            lane_means = (float(t["lanes"].double().mean()) for t in (mine, theirs))
            test = chi2_counts(mine["lanes"], theirs["lanes"], lanes)
            row("initial lanes", *lane_means, test)
        total = torch.zeros(episodes, dtype=torch.float64)
        alive = torch.ones(episodes, dtype=torch.bool)
        crashed = torch.zeros(episodes, dtype=torch.bool)
        while bool(alive.any()):
            td = env.step(policy(td.exclude("state")))
            nxt = td.get("next")
            total += nxt.get("reward").squeeze(-1).double() * alive
            crashed |= nxt.get("crashed").squeeze(-1) & alive
            alive &= ~nxt.get("done").squeeze(-1)
            td = nxt
        ref = reference["policies"][name]
        returns = torch.round(total, decimals=decimals)
        ref_returns = torch.round(
            torch.tensor(ref["returns"], dtype=torch.float64), decimals=decimals
        )
        row(
            f"{name}: return",
            float(total.mean()),
            float(ref_returns.mean()),
            ks_2samp(returns, ref_returns),
        )
        ref_crashed = torch.tensor(ref["crashed"])
        rates = (float(flags.double().mean()) for flags in (crashed, ref_crashed))
        row(f"{name}: crash rate", *rates, proportions_z(crashed, ref_crashed))
    return rows
