"""scripts/evaluate.py on forked workers against one process: wall-clock, and the same table.

The command of the claim is ``scripts/evaluate.py checkpoint=... episodes=200
baselines=[slower,rule]``: the trained policy (its first episode replayed as a GIF) and two
baselines on highway-env. This script runs :func:`~torchrl_grpo.training.evaluation.
evaluate_checkpoint` with that config twice, ``eval_workers=1`` then ``eval_workers=N``
(``--workers``; default: the usable cores), alternately ``--repeats`` times, and prints the
ratio of the wall-clocks (goal: at most 0.55 on 2 cores) and whether the two
``results.json`` are identical, episode for episode.

    python benchmarks/bench_evaluation.py --episodes 20          # a smoke checkpoint, made here
    python benchmarks/bench_evaluation.py --checkpoint outputs/.../last.pt --episodes 200

Without ``--checkpoint``, a smoke run (``experiment=smoke env.max_episode_steps=40``: a tiny
network, full-length episodes) is trained first; the evaluation's cost is highway-env's
steps, not the network's. On a machine busy with other work the wall-clock ratio says
little (a saturated machine gives two processes no more CPU than one): the CPU seconds of
both sides are printed beside it, with the load average.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from claims import claim

from torchrl_grpo.training import compose_config
from torchrl_grpo.training.eval_episodes import eval_workers
from torchrl_grpo.training.evaluation import evaluate_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def smoke_checkpoint(out: Path) -> Path:
    """Train the smoke preset with full-length evaluation episodes; its ``last.pt``."""
    args = ["experiment=smoke", "env.max_episode_steps=40", "logger=none"]
    args += ["experiment.final_eval_episodes=0", f"experiment.out_dir={out}"]
    subprocess.run([sys.executable, str(ROOT / "scripts" / "train.py"), *args], check=True)
    return out / "last.pt"


def timed(checkpoint: Path, episodes: int, baselines: list[str], workers: int, out: Path):
    cfg = compose_config(
        [
            f"checkpoint={checkpoint}",
            f"episodes={episodes}",
            f"baselines=[{','.join(baselines)}]",
            f"eval_workers={workers}",
        ],
        config_name="evaluate",
        conf_dir=ROOT / "conf",
    )
    start, cpu = time.perf_counter(), os.times()
    evaluate_checkpoint(cfg, out)
    seconds, end = time.perf_counter() - start, os.times()
    # This process's CPU and its workers' (reaped children), to tell work from waiting.
    here = sum(b - a for a, b in zip(cpu[:2], end[:2], strict=True))
    workers = sum(b - a for a, b in zip(cpu[2:4], end[2:4], strict=True))
    return seconds, (here, workers), json.loads((out / "results.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--baselines", nargs="*", default=["slower", "rule"])
    parser.add_argument("--workers", type=int, default=None, help="default: the usable cores")
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    workers = eval_workers(args.workers)
    if workers < 2:
        sys.exit("one worker: nothing to compare (give --workers 2 or more)")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        checkpoint = args.checkpoint or smoke_checkpoint(tmp / "run")
        times: dict[int, float] = {1: 0.0, workers: 0.0}
        cpu: dict[int, list[float]] = {1: [0.0, 0.0], workers: [0.0, 0.0]}
        tables: dict[int, list] = {}
        for r in range(args.repeats):
            # Alternately: what slows the machine down slows both sides.
            for n in (1, workers):
                seconds, cpu_seconds, tables[n] = timed(
                    checkpoint, args.episodes, args.baselines, n, tmp / f"eval_{n}_{r}"
                )
                times[n] += seconds
                cpu[n] = [c + d for c, d in zip(cpu[n], cpu_seconds, strict=True)]
                print(
                    f"eval_workers={n}: {seconds:.1f} s wall, CPU {cpu_seconds[0]:.1f} s here "
                    f"+ {cpu_seconds[1]:.1f} s in workers"
                )
    policies = 1 + len(args.baselines)
    print(
        f"{policies} policies x {args.episodes} episodes, {args.repeats} repeat(s): "
        f"1 worker {times[1]:.1f} s, {workers} workers {times[workers]:.1f} s"
    )
    print(f"load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    same = tables[1] == tables[workers]
    claim(
        f"evaluate.py: {workers} workers / 1 worker wall-clock",
        times[workers] / times[1],
        "<=0.55",
        note=f"{args.episodes} episodes per policy",
    )
    serial_cpu = sum(cpu[1])
    claim(
        f"evaluate.py: CPU seconds, {workers} workers / 1 worker",
        sum(cpu[workers]) / serial_cpu,
        note="above 1: work the workers add",
    )
    # On idle cores, this process's part plus the workers' shared evenly, against one
    # process's CPU: what the wall-clock ratio would be with nothing else running.
    claim(
        f"evaluate.py: {workers} workers / 1 worker, CPU-bound estimate on idle cores",
        (cpu[workers][0] + cpu[workers][1] / workers) / serial_cpu,
        note="an estimate from CPU seconds, not a timing",
    )
    claim("evaluate.py: tables of 1 and N workers identical (1 = yes)", float(same), ">=1")
    if not same:
        sys.exit("the tables differ")


if __name__ == "__main__":
    main()
