"""The learning curve of a pipeline (``algo.teacher_runs``) against counted frames and minutes.

A pipeline's network is the product of every stage before it: the teacher runs, then
each round's student. Its curve joins the stages' periodic evaluations end to end:
each stage's frames and training minutes start where the stages before it stopped, and
a student's frames include the search steps that labelled its states (each
evaluation's ``search_frames``; a run that recorded only its checkpoint's total, before
2026-12-04, has it spread over its evaluations in proportion to its own frames, as it
labels every state it visits). Every stage's first row (its frame 0,
the untrained network) is left out, so the axis shows the trained networks.
A plain run (PPO, say) is a pipeline of one stage, drawn beside. Stages run one after
another, except teachers trained in processes (``algo.teacher_processes > 1``): those
start at the same minute, each row keeps its own network's evaluation and minute, and
its frames are all of theirs by that minute.

    python benchmarks/bench_pipeline_curve.py runs/search_student_round2 runs/ppo15 \
        --labels "expert iteration, 2 rounds" PPO --out docs/img/search_student
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
from claims import claim

from torchrl_grpo.training import load_checkpoint, plot_learning_curve

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_pipeline_curve")


#: A stage's totals: its folder, and the pipeline's frames and minutes at its end.
Stage = tuple[Path, float, float]


def _stage_rows(checkpoint: dict) -> tuple[list[dict], float, float]:
    """One stage's rows (frames counted, ``minutes``) from its start; its frames and minutes."""
    own = checkpoint["eval_history"]  # eval_history.jsonl's rows
    search, final = int(checkpoint.get("search_frames") or 0), max(own[-1]["frames"], 1)
    rows = []
    for row in own[1:]:
        searched = row.get("search_frames", search * row["frames"] / final)
        rows.append(
            {**row, "frames": row["frames"] + searched, "minutes": row["wall_seconds"] / 60}
        )
    return rows, own[-1]["frames"] + search, own[-1]["wall_seconds"] / 60


def _side_by_side(lanes: list[tuple[list[dict], list[Stage]]]) -> tuple[list[dict], list[Stage]]:
    """Teacher pipelines trained at once, from the same minute, as one curve.

    A row keeps its own network's evaluation and minute; its frames are every lane's
    frames by that minute (another lane's read off its rows, linearly between them).
    """
    paths = [
        ([0.0] + [r["minutes"] for r in rows], [0.0] + [r["frames"] for r in rows])
        for rows, _ in lanes
    ]

    def frames_at(minutes: float) -> float:
        return float(sum(np.interp(minutes, times, frames) for times, frames in paths))

    rows = [{**r, "frames": frames_at(r["minutes"])} for lane, _ in lanes for r in lane]
    stages = [(path, frames_at(minutes), minutes) for _, lane in lanes for path, _, minutes in lane]
    return sorted(rows, key=lambda r: r["minutes"]), sorted(stages, key=lambda s: s[2])


def _curve(run: Path) -> tuple[list[dict], list[Stage]]:
    lanes = [
        _curve(teacher)
        for teacher in sorted((run / "teachers").glob("*"), key=lambda p: int(p.name))
    ]
    checkpoint = load_checkpoint(run / "last.pt")
    algo = (checkpoint.get("config") or {}).get("algo") or {}
    if len(lanes) > 1 and int(algo.get("teacher_processes") or 1) > 1:
        lanes = [_side_by_side(lanes)]
    own, frames, minutes = _stage_rows(checkpoint)
    lanes.append((own, [(run, frames, minutes)]))
    rows, stages, frames_before, minutes_before = [], [], 0.0, 0.0
    for lane_rows, lane_stages in lanes:  # one after another, the run's own stage last
        rows += [
            {**r, "frames": r["frames"] + frames_before, "minutes": r["minutes"] + minutes_before}
            for r in lane_rows
        ]
        stages += [(path, f + frames_before, m + minutes_before) for path, f, m in lane_stages]
        frames_before, minutes_before = stages[-1][1], stages[-1][2]
    return rows, stages


def pipeline_curve(run: Path) -> tuple[list[dict], list[tuple[str, float, float]]]:
    """The pipeline's rows (``frames`` counted, ``minutes``) and each stage's totals.

    Its teachers come first, one after another (depth first), or side by side when its
    config trained them in processes (``algo.teacher_processes > 1``); then ``run``.
    """
    rows, stages = _curve(run)
    return rows, [(str(path.relative_to(run.parent)), f, m) for path, f, m in stages]


def main() -> None:
    """Print each curve's table and claims, and draw the three curves."""
    p = argparse.ArgumentParser()
    p.add_argument("runs", nargs="+", type=Path, help="run folders: pipelines, or plain runs")
    p.add_argument("--labels", nargs="*", default=None, help="one per run folder")
    p.add_argument("--out", type=Path, default=Path("docs/img/pipeline"))
    args = p.parse_args()
    if args.labels is not None and len(args.labels) != len(args.runs):
        raise SystemExit(f"--labels takes one label per run: {len(args.runs)}, {len(args.labels)}")
    labels = args.labels or [str(folder) for folder in args.runs]

    curves = {}
    for label, folder in zip(labels, args.runs, strict=True):
        rows, stages = pipeline_curve(folder)  # a plain run: a pipeline of one stage
        curves[label] = [rows]
        print(f"\n{label} ({folder}):")
        print("| frames counted | minutes | return | crash rate | episodes (seeds) |")
        print("|---|---|---|---|---|")
        for row in rows:
            print(
                f"| {row['frames'] / 1e6:.2f}M | {row['minutes']:.1f} | {row['return']:.2f} | "
                f"{100 * row['crash_rate']:.1f}% | {int(row['episodes'])} ({row['seed']}..) |"
            )
        for name, frames, minutes in stages:
            print(f"  stage {name}: ends at {frames / 1e6:.2f}M frames, {minutes:.1f} minutes")
        claim(f"{label}: minutes of training end to end", rows[-1]["minutes"])
        claim(f"{label}: millions of frames, search steps included", rows[-1]["frames"] / 1e6)

    args.out.mkdir(parents=True, exist_ok=True)
    for metric, x, name in (
        ("return", "frames", "return_frames"),
        ("return", "minutes", "return_minutes"),
        ("crash_rate", "frames", "crash_rate_frames"),
    ):
        path = plot_learning_curve(
            curves,
            args.out / f"curve_{name}.png",
            metric=metric,
            x=x,
            title=f"highway-env evaluations ({metric}) against {x}"
            + (", search steps counted" if x == "frames" else " on 2 cores"),
        )
        log.info("wrote %s", path)


if __name__ == "__main__":
    main()
