"""Claim: GRPO with snapshot branching learns highway-fast-v0 at least as well as PPO per env frame.

Aggregates finished training runs (each a folder written by scripts/train.py, holding
config.yaml and eval_history.jsonl) into learning curves, mean ± std over seeds, one
PNG per env, and a Markdown table of the last evaluation of every run, beside the
scripted baselines evaluated on the same seeds.

    # 1. the runs (one per algo and seed; see docs/results.md for the exact commands)
    python scripts/train.py -m seed=0,1,2 algo=grpo_branch,grpo_episode,ppo \
        experiment.total_frames=20000 logger=csv
    # 2. the curves and the table
    python benchmarks/bench_training.py multirun/<day>/<time>/* --out docs/img
"""

import argparse
import json
import logging
import statistics
from collections import defaultdict
from pathlib import Path

from claims import claim
from omegaconf import OmegaConf

from torchrl_grpo.training import plot_learning_curve
from torchrl_grpo.training.evaluation import evaluate_checkpoint
from torchrl_grpo.training.resolvers import env_name

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_training")


def up_to(histories: dict[str, list[list[dict]]], cut: float) -> dict[str, list[list[dict]]]:
    """Each algorithm's histories, cut to the rows at or below ``cut`` frames."""
    return {a: [[r for r in h if r["frames"] <= cut] for h in hs] for a, hs in histories.items()}


p = argparse.ArgumentParser()
p.add_argument("runs", nargs="+", type=Path, help="run folders (config.yaml + eval_history.jsonl)")
p.add_argument("--out", type=Path, default=Path("docs/img"))
p.add_argument("--baseline-episodes", type=int, default=30)
p.add_argument(
    "--baselines",
    nargs="*",
    default=["idle", "slower", "rule"],
    help="scripted policies beside the curves; 'slower' also for the claim",
)
p.add_argument(
    "--max-frames",
    type=int,
    default=None,
    help="cut every curve here (default: the shortest run of each env)",
)
p.add_argument(
    "--labels",
    nargs="*",
    default=None,
    help="one curve label per run, in the order given (default: the run's algo); "
    "runs with one label are seeds of one curve",
)
args = p.parse_args()
if args.labels is not None and len(args.labels) != len(args.runs):
    raise SystemExit(
        f"--labels takes one label per run: {len(args.runs)} runs, {len(args.labels)} labels"
    )
labels = dict(zip(args.runs, args.labels, strict=True)) if args.labels else {}

curves = defaultdict(lambda: defaultdict(list))  # env -> algo -> [history]
periodic = defaultdict(lambda: defaultdict(list))  # the same, periodic evaluations only
rows = []
envs = {}
eval_seeds = defaultdict(set)  # env -> the runs' periodic seed sets
for run in sorted(args.runs):
    hist_path = run / "eval_history.jsonl"
    if not (run / "config.yaml").exists() or not hist_path.exists():
        continue
    cfg = OmegaConf.load(run / "config.yaml")
    history = [json.loads(line) for line in hist_path.read_text().splitlines() if line]
    if not history:
        continue
    env, algo = env_name(cfg.env.scenario), labels.get(run, str(cfg.algo.name))
    envs[env] = cfg.env
    curves[env][algo].append(history)
    # The final evaluation drives another seed set: only the periodic rows meet the
    # baselines below on their own episodes (rows written before they named their seed
    # tell the final one by its episode count).
    seed, size = int(cfg.experiment.eval_seed), int(cfg.experiment.eval_episodes)
    eval_seeds[env].add(seed)
    periodic[env][algo].append(
        [r for r in history if r.get("seed", seed) == seed and int(r["episodes"]) == size]
    )
    last = history[-1]
    rows.append((env, algo, int(cfg.seed), last))

args.out.mkdir(parents=True, exist_ok=True)
print("| env | algo | seed | frames | return | crash rate | speed | episodes |")
print("|---|---|---|---|---|---|---|---|")
for env, algo, seed, last in rows:
    print(
        f"| {env} | {algo} | {seed} | {last['frames']} | {last['return']:.2f} ± "
        f"{last['return_std']:.2f} | {100 * last['crash_rate']:.1f}% | {last['speed']:.1f} | "
        f"{int(last['episodes'])} |"
    )

for env, by_algo in curves.items():
    # Compare at the same frames: cut every run where the shortest one stops.
    # (5% slack: runs stop at the first batch boundary past their budget).
    cut = args.max_frames or 1.05 * min(h[-1]["frames"] for hs in by_algo.values() for h in hs)
    by_algo = up_to(by_algo, cut)
    hlines = {}
    if len(eval_seeds[env]) > 1:
        raise SystemExit(f"the runs of {env} evaluate on different seed sets: {eval_seeds[env]}")
    if args.baselines:
        base_cfg = OmegaConf.create(
            {
                "env": OmegaConf.to_container(envs[env]),
                "checkpoint": None,
                "episodes": args.baseline_episodes,
                "seed": next(iter(eval_seeds[env])),
                "baselines": list(args.baselines),
                "video": False,
            }
        )
        report = evaluate_checkpoint(base_cfg, args.out / f"baselines_{env}")
        print(f"\nbaselines on {env}:\n{report.table}")
        hlines = {r.name: r.summary()["return"] for r in report.results}
    for metric in ("return", "crash_rate"):
        path = plot_learning_curve(
            dict(by_algo),
            args.out / f"curve_{env}_{metric}.png",
            metric=metric,
            title=f"{envs[env].scenario}: deterministic evaluation ({metric})",
            hlines=hlines if metric == "return" else None,
        )
        log.info("wrote %s", path)
    path = plot_learning_curve(
        dict(by_algo),
        args.out / f"curve_{env}_return_wall.png",
        title=f"{envs[env].scenario}: deterministic evaluation (return, wall-clock)",
        hlines=hlines,
        x="wall_seconds",
    )
    log.info("wrote %s", path)
    # The claim: how soon each algorithm's greedy policy beats always-SLOWER. A run beats
    # it at its first evaluation whose return is above always-SLOWER's on the same
    # episodes (evaluation i of n episodes uses seed eval_seed + i, and so do baselines).
    slower = (
        next((r for r in report.results if r.name == "always-SLOWER"), None)
        if (args.baselines)
        else None
    )
    if slower is None:
        continue

    def slower_on(n: int, slower=slower) -> float:
        if n > len(slower.returns):
            raise SystemExit(f"--baseline-episodes must be >= {n}, the runs' evaluation size")
        return statistics.mean(slower.returns[:n])

    for algo, histories in up_to(periodic[env], cut).items():
        beaten = [
            next((r for r in h if r["return"] > slower_on(int(r["episodes"]))), None)
            for h in histories
        ]
        hits = [r for r in beaten if r is not None]
        if hits:
            frames = statistics.median(r["frames"] for r in hits)
            walls = [r["wall_seconds"] for r in hits if "wall_seconds" in r]
            wall = f", {statistics.median(walls):.0f} s of training" if walls else ""
            margin = statistics.median(r["return"] - slower_on(int(r["episodes"])) for r in hits)
            note = f"median of the runs that did: {frames:.0f} frames{wall}, by {margin:+.2f}"
        else:
            note = f"no run did within {cut:.0f} frames"
        # Beating it once is not keeping it: say where the runs ended.
        ahead = sum(h[-1]["return"] > slower_on(int(h[-1]["episodes"])) for h in histories if h)
        note += f"; {ahead} of {len(histories)} still ahead at their last evaluation"
        claim(
            f"{envs[env].scenario} {algo}: share of runs beating always-SLOWER",
            len(hits) / len(histories),
            ">=1.0",
            note=note,
        )
