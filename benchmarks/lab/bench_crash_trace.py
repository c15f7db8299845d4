"""How a run's crash rate moves from one iteration to the next, measured to a point.

Trains one run (``scripts/train.py``'s config and any overrides) with a hook that,
every ``--every`` iterations from ``--from-frames`` on, drives the averaged policy
greedily on the tensor simulator over ``--episodes`` episodes from highway-env's
seeds 30000.. (``bench_crash_rates.py``'s set) and ``--validation-episodes`` more from
seeds 40000... It prints each point's return and crash rate on both sets, the range
and mean of the crash rate, and the correlation of the two sets' crash rates: whether
a validation set of that size could pick a run's good checkpoints. The evaluations are
seeded and draw nothing from the training's generators, so the run trains exactly as
it would without them.

    python benchmarks/lab/bench_crash_trace.py --out runs/trace_s0 -- seed=0 \
        algo=grpo_branch algo.group_fit_coeff=1 algo.group_fit_loss=regression \
        algo.group_fit_temperature=1 model.crash_head=true model.crash_aversion=3 \
        optim.ema_decay=0.9 experiment.total_frames=1000000
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
from pathlib import Path

import torch

from torchrl_grpo.training import Trainer
from torchrl_grpo.training.compose import compose_config
from torchrl_grpo.training.hooks import Hook
from torchrl_grpo.training.transfer import evaluate_on_tensor

logging.basicConfig(level=logging.WARNING, format="%(message)s")

TEST_SEED, VALIDATION_SEED = 30_000, 40_000


class CrashTrace(Hook):
    """Every ``every`` iterations from ``start`` frames: the averaged policy on two seed sets."""

    phase = "crash_trace"

    def __init__(self, start: int, every: int, episodes: int, validation: int) -> None:
        self.start, self.every = start, every
        self.sets = (("test", episodes, TEST_SEED), ("validation", validation, VALIDATION_SEED))
        self.rows: list[dict] = []

    def due(self, trainer, batch) -> bool:  # noqa: D102
        return trainer.frames >= self.start and trainer.progress.iteration % self.every == 0

    def on_iteration(self, trainer, batch, result) -> dict:  # noqa: D102
        row = {"frames": trainer.frames, "iteration": trainer.progress.iteration}
        for name, episodes, seed in self.sets:
            res = evaluate_on_tensor(
                trainer.cfg.env, trainer.eval_policy, episodes=episodes, seed=seed
            )
            row[name] = (statistics.mean(res.returns), sum(res.crashed) / episodes)
        self.rows.append(row)
        return {}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="the run folder")
    p.add_argument("--from-frames", type=int, default=300_000)
    p.add_argument("--every", type=int, default=3, help="iterations between points")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--validation-episodes", type=int, default=500)
    p.add_argument("overrides", nargs="*", help="scripts/train.py overrides (after --)")
    args = p.parse_args()
    torch.set_num_threads(1)
    quiet = ["experiment.eval_every=0", "experiment.baselines=[]", "logger=csv"]
    quiet += ["experiment.plot_every=0", "experiment.progress_bar=false"]
    cfg = compose_config([*quiet, *args.overrides, f"experiment.out_dir={args.out}"])
    trace = CrashTrace(args.from_frames, args.every, args.episodes, args.validation_episodes)
    Trainer(cfg, hooks=[trace]).train()
    rows = trace.rows
    Path(args.out, "crash_trace.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    print("| frames | iteration | test return | test crash rate | validation crash rate |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['frames']} | {r['iteration']} | {r['test'][0]:.2f} | "
            f"{100 * r['test'][1]:.1f}% | {100 * r['validation'][1]:.1f}% |"
        )
    if len(rows) >= 2:
        test = [r["test"][1] for r in rows]
        validation = [r["validation"][1] for r in rows]
        try:
            corr = f"{statistics.correlation(test, validation):.2f}"
        except statistics.StatisticsError:  # a constant rate (no crash at all, say)
            corr = "undefined (a constant crash rate)"
        print(
            f"{len(rows)} points: test crash rate {100 * min(test):.1f}% to "
            f"{100 * max(test):.1f}% (mean {100 * statistics.mean(test):.1f}%); "
            f"correlation with the validation set's: {corr}"
        )


if __name__ == "__main__":
    main()
