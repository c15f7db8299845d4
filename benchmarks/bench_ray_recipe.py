"""The recipe's training frames/s on Ray actors against the local run, side by side.

    python benchmarks/bench_ray_recipe.py [--frames 60000] [--repeats 2] [--actors 1 2]

Each measurement is ``scripts/train.py``'s default config (GRPO with branching, rule
tails, replay, live trunks, on the tensor simulator) for ``--frames`` frames, with no
evaluation and no logger, in a fresh process: ``local`` as it trains by default, and
``rollout=ray`` with each number of ``--actors`` (each actor steps a shard of
``env.num_envs / actors`` worlds on one CPU, the learner updates in this process). The
kinds run in alternation, ``--repeats`` times, so that load from other processes hits
them alike. Frames/s are end to end (actor start, collection, updates), from the
trainer's own frame count and the process's wall time around ``Trainer.train``. It
prints the median of each kind, its ratio to ``local``, and the seconds the trainer
spent collecting (the actors' work and the transfer) and updating (the learner), from
its csv log: the split a projection to more actors needs, since only collection
scales with them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys

CHILD = """
import glob, json, sys, tempfile, time, warnings
warnings.filterwarnings("ignore")
from torchrl_grpo.training import Trainer, compose_config
overrides = json.loads(sys.argv[1])
cfg = compose_config(overrides)
with tempfile.TemporaryDirectory() as run_dir:
    start = time.perf_counter()
    result = Trainer(cfg, run_dir=run_dir).train()
    elapsed = time.perf_counter() - start
    phases = {}
    for phase in ("collect", "update"):
        (path,) = glob.glob(f"{run_dir}/csv/*/scalars/time/{phase}.csv")
        rows = open(path).read().split()
        phases[phase] = sum(float(r.split(",")[-1]) for r in rows)
print(json.dumps({"frames": int(result.frames), "seconds": elapsed, **phases}))
"""


def overrides(kind: str, frames: int) -> list[str]:
    """The config of one measurement: the recipe, short, locally or on ``kind`` actors."""
    base = [
        "logger=csv",
        f"experiment.total_frames={frames}",
        "experiment.eval_every=0",
        "experiment.final_eval_episodes=0",
        "experiment.checkpoint_every=1000",
    ]
    if kind == "local":
        return base
    return [*base, "rollout=ray", f"rollout.ray.num_actors={kind}"]


def measure(kind: str, frames: int) -> dict[str, float]:
    """Frames, wall seconds and the collect and update phases' seconds of one fresh run."""
    out = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(overrides(kind, frames))],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60_000)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    kinds = ["local", *(str(a) for a in args.actors)]
    runs: dict[str, list[dict[str, float]]] = {k: [] for k in kinds}
    for _ in range(args.repeats):
        for kind in kinds:
            runs[kind].append(measure(kind, args.frames))

    def median(kind: str, key: str) -> float:
        return statistics.median(r[key] for r in runs[kind])

    def rate(run: dict[str, float]) -> float:
        return run["frames"] / run["seconds"]

    local = statistics.median(rate(r) for r in runs["local"])
    print(f"recipe, {args.frames} frames, median of {args.repeats}")
    print("| run | frames/s | ratio to local | collect s | update s | wall s | runs (frames/s) |")
    print("|---|---|---|---|---|---|---|")
    for kind in kinds:
        fps = statistics.median(rate(r) for r in runs[kind])
        name = "local" if kind == "local" else f"rollout=ray, {kind} actor(s)"
        each = ", ".join(f"{rate(r):,.0f}" for r in runs[kind])
        print(
            f"| {name} | {fps:,.0f} | {fps / local:.2f} | {median(kind, 'collect'):.1f} "
            f"| {median(kind, 'update'):.1f} | {median(kind, 'seconds'):.1f} | {each} |"
        )


if __name__ == "__main__":
    main()
