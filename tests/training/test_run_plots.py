"""Every plot of the main job shows its data: read back each PNG it writes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image
from train_setup import compose_config

from torchrl_grpo.training import Trainer, load_checkpoint, plot_learning_curve
from torchrl_grpo.training.evaluation import evaluate_checkpoint

# A main-job-like run (one evaluation, at the end) on a tiny budget.
_MAIN_JOB = [
    "experiment=smoke",
    "experiment.eval_every=0",
    "experiment.total_frames=100",
    "logger=csv",
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


TAB = {"blue": (31, 119, 180), "orange": (255, 127, 14), "green": (44, 160, 44)}


def _mask(path, color):
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    return (np.abs(rgb - np.array(TAB[color])).max(-1) < 40).astype(int)


def _long_lines(mask, fraction=0.35):
    """Heights of the horizontal lines crossing most of the figure (one per panel)."""
    rows = np.nonzero(mask.sum(1) > fraction * mask.shape[1])[0]
    return [int(r) for i, r in enumerate(rows) if i == 0 or r > rows[i - 1] + 2]


def _blobs(mask):
    """Bounding boxes (height, width) of 8-connected groups of pixels."""
    todo = {(int(y), int(x)) for y, x in zip(*np.nonzero(mask), strict=True)}
    boxes = []
    while todo:
        stack, ys, xs = [todo.pop()], [], []
        while stack:
            y, x = stack.pop()
            ys.append(y)
            xs.append(x)
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    if (y + dy, x + dx) in todo:
                        todo.remove((y + dy, x + dx))
                        stack.append((y + dy, x + dx))
        boxes.append((max(ys) - min(ys) + 1, max(xs) - min(xs) + 1))
    return boxes


def test_the_run_curve_has_baseline_lines_a_final_star_and_a_crash_panel(tmp_path):
    from torchrl_grpo.training.results import EvalResult
    from torchrl_grpo.training.run_plots import plot_run_curve

    def row(frames, ret, crash, seed):
        return {"frames": frames, "return": ret, "crash_rate": crash, "seed": seed, "episodes": 4}

    history = [row(0, 8.0, 0.75, 10), row(100, 12.0, 0.5, 10), row(200, 14.0, 0.25, 10)]
    history.append(row(250, 15.0, 0.1, 20))  # the final evaluation, on its own seeds

    def baseline(name, ret, crashes, first_seed):
        seeds = list(range(first_seed, first_seed + 4))
        return EvalResult(name, [ret] * 4, crashes, [30] * 4, [20.0] * 4, seeds)

    # Returns and crash rates apart from the curve's: each line stands alone.
    slower = baseline("always-SLOWER", 10.0, [False, True, True, True], 10)
    rule = baseline("rule policy", 16.0, [False] * 4, 10)
    paths = {}
    for final in (True, False):
        rows = history if final else history[:-1]
        paths[final] = plot_run_curve(
            rows, tmp_path / f"c{final}.png", label="grpo", final_seed=20, baselines=[slower, rule]
        )
    # Each baseline is a horizontal line in both panels: return (top), crash rate (below).
    for color in ("orange", "green"):
        lines = _long_lines(_mask(paths[True], color))
        assert len(lines) == 2, (color, lines)
    height = np.asarray(Image.open(paths[True])).shape[0]
    orange, green = (
        _long_lines(_mask(paths[True], "orange")),
        _long_lines(_mask(paths[True], "green")),
    )
    # Top panel: SLOWER's return below the rule's; crash panel: SLOWER's 75% above 0%.
    assert orange[0] > green[0] and orange[1] < green[1] and orange[1] > height / 2
    # The final evaluation is a star of its own in each panel (and in the legend); the
    # periodic points are small markers on their line.
    stars = [b for b in _blobs(_mask(paths[True], "blue")) if b[0] >= 10 and 10 <= b[1] <= 30]
    assert len(stars) == 3, stars
    assert not [b for b in _blobs(_mask(paths[False], "blue")) if b[0] >= 10 and b[1] <= 30]


@pytest.mark.slow  # two training runs: 20 s on 2 busy cores
def test_a_frame_zero_evaluation_leaves_the_weights_and_the_table_as_they_were(
    tmp_path, monkeypatch
):
    from torchrl_grpo.training.hooks import EvaluationHook, Hook

    overrides = [
        "experiment=smoke",
        "logger=none",
        "experiment.total_frames=120",
        "experiment.eval_every=1",
        "experiment.final_eval_episodes=1",
    ]
    runs = {}
    for frame_zero in (True, False):
        if not frame_zero:
            monkeypatch.setattr(EvaluationHook, "on_train_start", Hook.on_train_start)
        result = Trainer(compose_config(overrides), run_dir=tmp_path / str(frame_zero)).train()
        runs[frame_zero] = (result, load_checkpoint(result.checkpoint))
    (result, with_zero), (_, without) = runs[True], runs[False]
    assert result.iterations >= 2
    history = [
        {k: v for k, v in r.items() if k != "wall_seconds"} for r in with_zero["eval_history"]
    ]
    others = [{k: v for k, v in r.items() if k != "wall_seconds"} for r in without["eval_history"]]
    assert history[0]["frames"] == 0 and history[0]["seed"] == 10_000
    assert history[1:] == others and all(r["frames"] > 0 for r in others)
    for name, tensor in with_zero["policy"].items():
        assert torch.equal(tensor, without["policy"][name]), name
    assert (tmp_path / "True" / "results.md").read_text() == (
        tmp_path / "False" / "results.md"
    ).read_text()


def test_evaluate_py_draws_the_baselines_the_run_cached_on_its_periodic_seeds(tmp_path):
    from torchrl_grpo.training.baseline_cache import cache_key, write_cached
    from torchrl_grpo.training.evaluation import _curve
    from torchrl_grpo.training.results import EvalResult

    run_cfg = compose_config(["experiment=smoke", f"experiment.baseline_cache={tmp_path}"])
    exp = run_cfg.experiment
    seeds = list(range(exp.eval_seed, exp.eval_seed + exp.eval_episodes))
    n = len(seeds)
    slower = EvalResult("always-SLOWER", [9.0] * n, [True] * n, [5] * n, [20.0] * n, seeds)
    key = cache_key(run_cfg.env, "slower", exp.eval_seed, exp.eval_episodes, run_cfg.seed)
    write_cached(tmp_path / key, slower)
    history = [
        {"frames": f, "return": r, "crash_rate": 0.0, "seed": exp.eval_seed, "episodes": n}
        for f, r in ((0, 10.0), (100, 14.0))
    ]
    trained = EvalResult("grpo", [15.0, 16.0], [False] * 2, [20] * 2, [21.0] * 2, [20000, 20001])
    path = _curve(run_cfg, history, [trained], 150, tmp_path / "eval")
    # The cached baseline: a line across each panel (its return, its 100% crash rate).
    assert len(_long_lines(_mask(path, "orange"))) == 2
    stars = [b for b in _blobs(_mask(path, "blue")) if b[0] >= 10 and 10 <= b[1] <= 30]
    assert len(stars) == 3, stars  # this evaluation: a star in each panel and the legend
