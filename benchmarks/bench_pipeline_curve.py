"""The learning curve of a pipeline (``algo.teacher_runs``) against counted frames and minutes.

A pipeline's network is the product of every stage before it: the teacher runs, then
each round's student. Its curve joins the stages' periodic evaluations end to end:
each stage's frames and training minutes start where the stages before it stopped, and
a student's frames include the search steps that labelled its states (each
evaluation's ``search_frames``; a run that recorded only its checkpoint's total, before
2026-12-04, has it spread over its evaluations in proportion to its own frames, as it
labels every state it visits). Every stage's first row (its frame 0,
the untrained network) is left out, so the axis shows the trained networks.
A plain run (PPO, say) is a pipeline of one stage, drawn beside. The minutes assume
the stages ran one after another, as they do unless ``algo.teacher_processes > 1``.

    python benchmarks/bench_pipeline_curve.py runs/search_student_round2 runs/ppo15 \
        --labels "expert iteration, 2 rounds" PPO --out docs/img/search_student
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from claims import claim

from torchrl_grpo.training import load_checkpoint, plot_learning_curve

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_pipeline_curve")


def stage_folders(run: Path) -> list[Path]:
    """The stage folders in the order they train: the teachers (depth first), then ``run``."""
    teachers = sorted((run / "teachers").glob("*"), key=lambda p: int(p.name))
    return [folder for teacher in teachers for folder in stage_folders(teacher)] + [run]


def pipeline_curve(run: Path) -> tuple[list[dict], list[tuple[str, int, float]]]:
    """The pipeline's rows (``frames`` counted, ``minutes``) and each stage's totals."""
    rows, stages, frames_before, seconds_before = [], [], 0, 0.0
    for folder in stage_folders(run):
        # The checkpoint holds the evaluations (eval_history.jsonl's rows) and the search's count.
        checkpoint = load_checkpoint(folder / "last.pt")
        own = checkpoint["eval_history"]
        search, final = int(checkpoint.get("search_frames") or 0), max(own[-1]["frames"], 1)
        for row in own[1:]:
            searched = row.get("search_frames", search * row["frames"] / final)
            counted = row["frames"] + searched
            rows.append(
                {
                    **row,
                    "frames": frames_before + counted,
                    "minutes": (seconds_before + row["wall_seconds"]) / 60,
                }
            )
        frames_before += own[-1]["frames"] + search
        seconds_before += own[-1]["wall_seconds"]
        stages.append((str(folder.relative_to(run.parent)), frames_before, seconds_before / 60))
    return rows, stages


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
        claim(f"{label}: minutes of training, stages one after another", rows[-1]["minutes"])
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
