"""Every plot of the main job shows its data: read back each PNG it writes."""

from __future__ import annotations

import json

import numpy as np
from PIL import Image
from train_setup import compose_config

from torchrl_grpo.training import Trainer, load_checkpoint, plot_learning_curve
from torchrl_grpo.training.evaluation import evaluate_checkpoint

# A main-job-like run (one evaluation, at the end) on a tiny budget.
_MAIN_JOB = [
    "experiment=smoke",
    "experiment.eval_every=0",
    "experiment.plot_every=1",
    "experiment.total_frames=100",
    "logger=csv",
    "logger.video=false",
]


def colored_blobs(path) -> int:
    """Connected groups of colored pixels (data) in a PNG; text, axes and grid are gray."""
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    colored = (rgb.max(-1) - rgb.min(-1)) > 60
    todo = {(int(y), int(x)) for y, x in zip(*np.nonzero(colored), strict=True)}
    count = 0
    while todo:  # flood fill, 8-connected
        count += 1
        stack = [todo.pop()]
        while stack:
            y, x = stack.pop()
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    if (y + dy, x + dx) in todo:
                        todo.remove((y + dy, x + dx))
                        stack.append((y + dy, x + dx))
    return count


def test_colored_blobs_sees_a_one_point_line_only_with_a_marker(tmp_path):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    counts = []
    for marker in (None, "o"):
        fig = Figure(figsize=(4, 3), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(1, 1, 1)
        ax.plot([5.0], [1.0], marker=marker, label="run")
        ax.legend()
        fig.savefig(tmp_path / "p.png")
        counts.append(colored_blobs(tmp_path / "p.png"))
    # The legend's handle alone; then the point too.
    assert counts == [1, 2]


def test_a_one_point_learning_curve_has_a_marker(tmp_path):
    path = plot_learning_curve({"a": [[{"frames": 100, "return": 3.0}]]}, tmp_path / "c.png")
    assert colored_blobs(path) >= 2


def test_every_plot_of_the_main_job_shows_its_data(tmp_path):
    cfg = compose_config(_MAIN_JOB)
    result = Trainer(cfg, run_dir=tmp_path / "run").train()
    assert result.curve is not None and result.iterations >= 2
    # The checkpoint holds the final evaluation: evaluate.py draws the curve from it.
    history = load_checkpoint(result.checkpoint)["eval_history"]
    rows = (tmp_path / "run" / "eval_history.jsonl").read_text().splitlines()
    assert history == [json.loads(row) for row in rows] and len(history) == 1
    eval_cfg = compose_config(
        [f"checkpoint={result.checkpoint}", "episodes=2", "baselines=[slower]", "video=false"],
        config_name="evaluate",
    )
    report = evaluate_checkpoint(eval_cfg, tmp_path / "run" / "eval")
    assert {"bars", "curve"} <= set(report.files)
    pngs = sorted((tmp_path / "run").rglob("*.png"))
    names = {p.relative_to(tmp_path / "run").as_posix() for p in pngs}
    assert {"learning_curve.png", "eval/learning_curve.png", "eval/comparison.png"} <= names
    assert any(name.startswith("plots/group_it") for name in names)
    for png in pngs:
        assert colored_blobs(png) >= 2, f"{png.name} draws no data"
