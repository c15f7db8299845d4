"""Helpers shared by the end-to-end training tests: tiny runs and their logged scalars.

A plain module rather than conftest.py, whose name other test folders share.
"""

from __future__ import annotations

import csv

from train_setup import TINY, compose_config

from torchrl_grpo.training import Trainer


def csv_scalars(run_dir) -> dict[str, list[float]]:
    """Every scalar a run logged to csv, by tag."""
    [exp] = list((run_dir / "csv").iterdir())
    out = {}
    for path in (exp / "scalars").rglob("*.csv"):
        with open(path) as f:
            out[str(path.relative_to(exp / "scalars").with_suffix(""))] = [
                float(row[1]) for row in csv.reader(f)
            ]
    return out


def logged_ratios(scalars: dict[str, list[float]], weighted: str, raw: str) -> list[float]:
    """``weighted / raw`` at every logged iteration: a loss term over its unweighted value."""
    return [w / r for w, r in zip(scalars[weighted], scalars[raw], strict=True)]


def train_run(tmp_path, name: str, overrides: list[str]) -> Trainer:
    """Train a tiny run (``TINY`` plus ``overrides``) in ``tmp_path / name``."""
    cfg = compose_config([*TINY, *overrides])
    trainer = Trainer(cfg, run_dir=tmp_path / name)
    trainer.train()
    return trainer


# The settings the recipes fix are keys of the experimental algo=grpo_lab (model=lab);
# with experiment=smoke it runs whole trunks, queued, as the smoke runs did before.
LAB = ["algo=grpo_lab", "model=lab"]

# Enumerated groups scored by a scripted tail, replayed for 50 groups.
REPLAY = [
    *LAB,
    "algo.group_size=5",
    "rollout.horizon=2",
    "rollout.decision_interval=2",
    "algo.explore_steps=1",
    "algo.first_action=enumerate",
    "algo.tail_policy=slower",
    "algo.replay_groups=50",
]
