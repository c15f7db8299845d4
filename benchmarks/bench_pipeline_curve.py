"""The learning curve of a pipeline (``algo.teacher_runs``) against counted frames and minutes.

A pipeline's network is the product of every stage before it: the teacher runs, then
each round's student. Its curve joins the stages' periodic evaluations end to end:
each stage's frames and training minutes start where the stages before it stopped, and
a student's frames include the search steps that labelled its states
(``search_frames`` in its checkpoint; spread over its evaluations in proportion to its
own frames, as it labels every state it visits). Every stage's first row (its frame 0,
the untrained network) is left out, so the axis shows the trained networks.
Plain runs (PPO, say) are drawn beside. The minutes assume the stages ran one after
another, as they do unless ``algo.teacher_processes > 1``.

    python benchmarks/bench_pipeline_curve.py --pipeline runs/search_student_round2 \
        --runs runs/ppo15 --labels "expert iteration, 2 rounds" PPO --out docs/img/search_student
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import torch
from claims import claim
from omegaconf import OmegaConf

from torchrl_grpo.training import plot_learning_curve

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_pipeline_curve")


def stage_folders(run: Path) -> list[Path]:
    """The stage folders in the order they train: the teachers (depth first), then ``run``."""
    teachers = sorted((run / "teachers").glob("*"), key=lambda p: int(p.name))
    return [folder for teacher in teachers for folder in stage_folders(teacher)] + [run]


def history(folder: Path) -> list[dict]:
    """A stage's ``eval_history.jsonl`` rows (an error naming the folder when it has none)."""
    path = folder / "eval_history.jsonl"
    if not path.exists():
        raise SystemExit(f"{folder} has no eval_history.jsonl: not a finished run folder")
    return [json.loads(line) for line in path.read_text().splitlines() if line]


def pipeline_curve(run: Path) -> tuple[list[dict], list[tuple[str, int, float]]]:
    """The pipeline's rows (``frames`` counted, ``minutes``) and each stage's totals."""
    rows, stages, frames_before, seconds_before = [], [], 0, 0.0
    for folder in stage_folders(run):
        own = history(folder)
        checkpoint = torch.load(folder / "last.pt", map_location="cpu", weights_only=False)
        search, final = int(checkpoint.get("search_frames") or 0), max(own[-1]["frames"], 1)
        for row in own[1:]:
            counted = row["frames"] + search * row["frames"] / final
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
    p.add_argument("--pipeline", nargs="*", type=Path, default=[], help="pipeline run folders")
    p.add_argument("--runs", nargs="*", type=Path, default=[], help="plain runs beside")
    p.add_argument("--labels", nargs="*", default=None, help="one per folder, pipelines first")
    p.add_argument("--out", type=Path, default=Path("docs/img/pipeline"))
    args = p.parse_args()
    folders = [*args.pipeline, *args.runs]
    if args.labels is not None and len(args.labels) != len(folders):
        raise SystemExit(f"--labels takes one label per folder: {len(folders)}, {len(args.labels)}")
    labels = args.labels or [str(folder) for folder in folders]

    curves = {}
    for label, folder in zip(labels, folders, strict=True):
        if folder in args.pipeline:
            rows, stages = pipeline_curve(folder)
        else:
            rows = [{**r, "minutes": r["wall_seconds"] / 60} for r in history(folder)[1:]]
            stages = [(folder.name, rows[-1]["frames"], rows[-1]["minutes"])]
        curves[label] = [rows]
        cfg = OmegaConf.load(folder / "config.yaml")
        print(f"\n{label} ({folder}, {cfg.algo.name}):")
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
