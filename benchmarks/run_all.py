"""Run every benchmark script and write the table of the benchmarks page.

Each script prints its claims through ``claims.claim``; with ``BENCH_CLAIMS`` set to a
file, it also records them there. This script runs the scripts one after the other
(they time things: never two at once), gathers the claims and writes
``docs/benchmarks.md``: one row per claim with the measured value, its goal and
whether it is met, and the command that measured it.

    python benchmarks/run_all.py                       # all scripts, docs/benchmarks.md
    python benchmarks/run_all.py --only env loss       # some of them
    python benchmarks/run_all.py --training-runs multirun/<day>/<time>/*   # + training

The training claim needs finished training runs (docs/lab/highway_workers.md, "How soon
a learner beats always-SLOWER", gives the commands that make them); without
``--training-runs`` it is not measured.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import torchrl

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

# name -> (script, arguments, what it is for)
SCRIPTS: dict[str, tuple[str, list[str], str]] = {
    "env": ("bench_env.py", [], "env overhead, snapshot + restore, state size"),
    "branching": ("bench_branching.py", [], "branch throughput against workers"),
    "ceiling": ("bench_ceiling.py", [], "branch workers against raw highway-env processes"),
    "loss": ("bench_loss.py", [], "GRPOLoss against ClipPPOLoss"),
    "loss_checks": ("bench_loss_checks.py", [], "GRPOLoss's value checks on against off"),
    "ray": ("bench_ray.py", [], "groups/s on Ray against the local collector"),
    "evaluation": (
        "bench_evaluation.py",
        ["--episodes", "20"],
        "evaluate.py on worker processes against one, the same table",
    ),
}


def run_script(script: str, arguments: list[str], sink: Path) -> tuple[int, str, float]:
    """Run one script with ``BENCH_CLAIMS=sink``; return its exit code, output and seconds."""
    env = dict(os.environ, BENCH_CLAIMS=str(sink), PYTHONWARNINGS="ignore")
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, str(HERE / script), *arguments],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    return proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - start


def fmt(value: float) -> str:
    return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"


def page(rows: list[dict], runs: list[dict], started: str) -> str:
    met = sum(r["met"] is True for r in rows)
    goals = sum(r["met"] is not None for r in rows)
    load = os.getloadavg()
    lines = [
        "# Benchmarks",
        "",
        "Every claim this project makes about speed or size, measured side by side in one",
        "run (a ratio of two things timed alternately on the same machine, so that what",
        "slows the machine down slows both sides). Written by `python benchmarks/run_all.py`;",
        "each row's command measures it alone.",
        "",
        f"Measured {started} on {os.cpu_count()} CPU cores ({platform.processor() or 'cpu'}),",
        f"Python {platform.python_version()}, torch {torch.__version__}, torchrl",
        f"{torchrl.__version__}; load average at the end {load[0]:.1f}. **{met} of {goals}",
        "goals met.**",
        "",
        "| claim | measured | goal | met | command |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        verdict = {True: "yes", False: "**no**", None: "(information)"}[r["met"]]
        value = fmt(r["value"]) + (f" ({r['note']})" if r["note"] else "")
        goal = r["goal"] or ""
        lines.append(f"| {r['claim']} | {value} | {goal} | {verdict} | `{r['command']}` |")
    if not any(run["command"].startswith("python benchmarks/bench_training.py") for run in runs):
        lines += [
            "",
            "The training claim (how soon GRPO beats always-SLOWER on highway-fast-v0) was not",
            "measured in this run: it needs finished training runs (`--training-runs`, see the",
            '[lab notes](lab/highway_workers.md), "How soon a learner beats always-SLOWER").',
        ]
    lines += [
        "",
        "## Runs",
        "",
        "| script | what it measures | exit | seconds |",
        "|---|---|---|---|",
    ]
    for run in runs:
        lines.append(
            f"| `{run['command']}` | {run['what']} | {run['exit']} | {run['seconds']:.0f} |"
        )
    # Hand-written sections (profiles, analyses) follow the measured table.
    for notes in sorted((HERE / "notes").glob("*.md")):
        lines += ["", notes.read_text().rstrip()]
    failed = [run for run in runs if run["exit"] != 0]
    for run in failed:
        lines += ["", f"### `{run['command']}` failed", "", "```", run["tail"], "```"]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=sorted(SCRIPTS), help="scripts to run")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md")
    parser.add_argument(
        "--training-runs",
        nargs="+",
        type=Path,
        default=None,
        help="finished training run folders: adds the training claim (bench_training.py)",
    )
    args = parser.parse_args()
    chosen = dict(SCRIPTS)
    if args.only:
        chosen = {k: v for k, v in chosen.items() if k in args.only}
    if "ray" in chosen and importlib.util.find_spec("ray") is None:
        print("skipping bench_ray.py: Ray is not installed (pip install -e '.[ray]')")
        chosen.pop("ray")
    if args.training_runs:
        out = tempfile.mkdtemp(prefix="bench_training_")
        run_args = [*map(str, args.training_runs), "--out", out]
        chosen["training"] = ("bench_training.py", run_args, "training runs against baselines")
    started = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    rows: list[dict] = []
    runs: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, (script, arguments, what) in chosen.items():
            sink = Path(tmp) / f"{name}.jsonl"
            command = shlex.join(["python", f"benchmarks/{script}", *arguments])
            print(f"+ {command}", flush=True)
            code, output, seconds = run_script(script, arguments, sink)
            print(output, flush=True)
            claims = (
                [json.loads(line) for line in sink.read_text().splitlines()]
                if (sink.exists())
                else []
            )
            rows += [{**c, "command": command} for c in claims]
            tail = "\n".join(output.strip().splitlines()[-15:])
            runs.append(
                {"command": command, "what": what, "exit": code, "seconds": seconds, "tail": tail}
            )
    args.out.write_text(page(rows, runs, started))
    print(f"wrote {args.out}")
    return 1 if any(run["exit"] != 0 for run in runs) else 0


if __name__ == "__main__":
    sys.exit(main())
