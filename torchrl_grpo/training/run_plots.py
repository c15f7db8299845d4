"""All the plots of a run: the learning curve, the policies compared, a GIF of an episode.

Figures are drawn with Matplotlib's object API on an Agg canvas (no display, no global
state), then written to PNG; videos are written as GIFs with Pillow. The branch-group
plots are :func:`torchrl_grpo.branching.plot_group`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from torchrl_grpo.training.results import EvalResult

__all__ = ["plot_comparison", "plot_learning_curve", "plot_run_curve", "save_gif"]


def plot_learning_curve(
    runs: dict[str, list[list[dict[str, float]]]],
    path: str | Path,
    *,
    metric: str = "return",
    title: str | None = None,
    hlines: dict[str, float] | None = None,
    x: str = "frames",
) -> Path:
    """Plot ``metric`` against frames (or ``x``): one line per label, mean ± std over its runs.

    Args:
        runs: ``{label: [history of run 1, history of run 2, ...]}``, each history a
            list of ``{"frames": ..., metric: ...}`` rows (``eval_history.jsonl``).
        path: PNG to write.
        metric: the key to plot.
        title: figure title.
        hlines: horizontal reference lines ``{label: value}`` (baselines).
        x: the key on the x axis: ``"frames"``, or ``"wall_seconds"`` (training time).

    Example:
        >>> import tempfile
        >>> h = [{"frames": 0, "return": 1.0}, {"frames": 10, "return": 2.0}]
        >>> plot_learning_curve({"a": [h, h]}, tempfile.mkdtemp() + "/c.png").suffix
        '.png'
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for label, histories in runs.items():
        # At equal frames keep the last row: the final evaluation (more episodes).
        histories = [list({r["frames"]: r for r in h}.values()) for h in histories if h]
        if not histories:
            continue
        grid = np.unique(np.concatenate([[r[x] for r in h] for h in histories]))
        curves = np.stack(
            [np.interp(grid, [r[x] for r in h], [r[metric] for r in h]) for h in histories]
        )
        mean, std = curves.mean(0), curves.std(0)
        # Markers: every evaluation shows, the first alone too (a line needs two points).
        runs_label = f"{label} ({len(histories)} run{'s' if len(histories) > 1 else ''})"
        line = ax.plot(grid, mean, marker="o", markersize=4, label=runs_label)[0]
        if len(histories) > 1:
            ax.fill_between(grid, mean - std, mean + std, color=line.get_color(), alpha=0.2)
    for label, value in (hlines or {}).items():
        ax.axhline(value, ls="--", lw=1, color="gray")
        ax.text(ax.get_xlim()[0], value, f" {label}", va="bottom", fontsize=8, color="gray")
    ax.set_xlabel(
        "env frames (every branch and trunk step)" if x == "frames" else f"{x} of training"
    )
    ax.set_ylabel(f"evaluation {metric}")
    if title:
        ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


#: Colours of the run's curve and of the baselines (in order); gray is left to text and grid.
_RUN_COLOR = "tab:blue"
_BASELINE_COLORS = ("tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive")


def seed_span(seed: int, episodes: int) -> str:
    """The seed set of ``episodes`` episodes from ``seed``, as a legend names it.

    Example:
        >>> seed_span(10_000, 30)
        'seeds 10000..10029'
    """
    return f"seeds {seed}..{seed + episodes - 1}" if episodes > 1 else f"seed {seed}"


def plot_run_curve(
    history: Sequence[Mapping[str, float]],
    path: str | Path,
    *,
    label: str,
    final_seed: int | None = None,
    baselines: Sequence[EvalResult] = (),
    final: Sequence[EvalResult] = (),
    final_frames: int | None = None,
    title: str | None = None,
) -> Path:
    """One run's learning curve: return and crash rate against frames, baselines beside it.

    Two panels share the frames axis: evaluation return on top, crash rate below. The
    periodic evaluations (rows of ``eval_history.jsonl`` whose seed is not
    ``final_seed``) are one line; the final evaluation is a star, its seed set in the
    legend. Each baseline of ``baselines`` (evaluated on the periodic seed set) is a
    labelled horizontal line; each of ``final`` (the final seed set; the trained policy
    first, when no history row is final) a marker at ``final_frames``. A curve without
    a frame-0 evaluation says where it starts.

    Args:
        history: evaluation rows: ``frames``, ``return``, ``crash_rate``, ``seed``,
            ``episodes``.
        path: PNG to write.
        label: the trained policy's name.
        final_seed: the first seed of the final evaluation (its rows become the star).
        baselines: baseline results on the periodic seed set.
        final: results on the final seed set drawn at ``final_frames`` (the trained
            policy's first if no history row is final, then the baselines').
        final_frames: where ``final`` is drawn (default: the last row's frames).
        title: figure title.

    Example:
        >>> import tempfile
        >>> h = [{"frames": 0, "return": 9.0, "crash_rate": 0.5, "seed": 10, "episodes": 2},
        ...      {"frames": 50, "return": 12.0, "crash_rate": 0.0, "seed": 20, "episodes": 4}]
        >>> slower = EvalResult("always-SLOWER", [10.0, 11.0], [False] * 2, [9, 9], [20.0] * 2,
        ...                     [10, 11])
        >>> plot_run_curve(h, tempfile.mkdtemp() + "/c.png", label="grpo", final_seed=20,
        ...                baselines=[slower]).suffix
        '.png'
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 6.5), dpi=100)
    FigureCanvasAgg(fig)
    ax_ret, ax_crash = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    panels = ((ax_ret, "return", 1.0), (ax_crash, "crash_rate", 100.0))
    periodic = [r for r in history if final_seed is None or r.get("seed") != final_seed]
    finals = [r for r in history if final_seed is not None and r.get("seed") == final_seed]
    if periodic:
        first = periodic[0]
        seeds = (
            f", {seed_span(int(first['seed']), int(first['episodes']))}" if "seed" in first else ""
        )
        xs = [r["frames"] for r in periodic]
        for ax, key, scale in panels:
            ys = [scale * r[key] for r in periodic]
            ax.plot(xs, ys, color=_RUN_COLOR, marker="o", markersize=4, label=f"{label}{seeds}")
        if xs[0] > 0:
            ax_ret.annotate(
                f"no frame-0 evaluation: the curve starts at {xs[0]:,} frames",
                (0.01, 0.02),
                xycoords="axes fraction",
                fontsize=8,
                color="gray",
            )
    end = final_frames if final_frames is not None else (history[-1]["frames"] if history else 0)
    for row in finals[-1:]:
        span = seed_span(int(row["seed"]), int(row["episodes"]))
        for ax, key, scale in panels:
            ax.plot(
                [row["frames"]],
                [scale * row[key]],
                ls="",
                marker="*",
                markersize=14,
                color=_RUN_COLOR,
                markeredgecolor="black",
                zorder=4,  # above the baselines' diamonds at the same frames
                label=f"{label}, final: {span}",
            )
        end = row["frames"] if final_frames is None else end
    colors = iter(_BASELINE_COLORS * 4)
    color_of = {}
    for res in baselines:
        color = color_of.setdefault(res.name, next(colors))
        s = res.summary()
        span = seed_span(min(res.seeds), len(res.seeds)) if res.seeds else ""
        for ax, key, scale in panels:
            ax.axhline(scale * s[key], ls="--", lw=1.5, color=color, label=f"{res.name}, {span}")
    for i, res in enumerate(final):
        trained = i == 0 and not finals
        color = _RUN_COLOR if trained else color_of.setdefault(res.name, next(colors))
        s = res.summary()
        span = seed_span(min(res.seeds), len(res.seeds)) if res.seeds else ""
        what = f"{label}, final: {span}" if trained else f"{res.name}, final: {span}"
        for ax, key, scale in panels:
            ax.plot(
                [end],
                [scale * s[key]],
                ls="",
                marker="*" if trained else "D",
                markersize=14 if trained else 7,
                color=color,
                markeredgecolor="black",
                zorder=4 if trained else 3,
                label=what,
            )
    # Crash rates start at 0 (all zero: a 0..10% panel, not matplotlib's 1e-17 scale).
    tops = [max(line.get_ydata(), default=0.0) for line in ax_crash.get_lines()]
    top = max(10.0, 1.15 * max(tops, default=0.0))
    ax_crash.set_ylim(-0.08 * top, top)  # room below 0 for a whole star
    ax_ret.set_ylabel("evaluation return")
    ax_crash.set_ylabel("crash rate (%)")
    ax_crash.set_xlabel("env frames (every branch and trunk step)")
    for ax in (ax_ret, ax_crash):
        ax.grid(alpha=0.3)
    if title:
        ax_ret.set_title(title)
    handles, labels = ax_ret.get_legend_handles_labels()
    if handles:
        # Below the panels: it hides no point.
        fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
    rows = (len(handles) + 1) // 2
    fig.tight_layout(rect=(0, min(0.035 * rows + 0.03, 0.45), 1, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def plot_comparison(results: Sequence[EvalResult], path: str | Path, title: str = "") -> Path:
    """Bar charts of return (mean ± std) and crash rate, one bar per policy.

    Example:
        >>> import tempfile
        >>> r = EvalResult("a", [1.0, 2.0], [False, True], [3, 3], [20.0, 21.0])
        >>> plot_comparison([r], tempfile.mkdtemp() + "/bars.png").suffix
        '.png'
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.8), dpi=100)
    FigureCanvasAgg(fig)
    ax_ret, ax_crash, ax_speed = fig.subplots(1, 3)
    names = [r.name for r in results]
    summaries = [r.summary() for r in results]
    x = np.arange(len(results))
    ax_ret.bar(
        x,
        [s["return"] for s in summaries],
        yerr=[s["return_std"] for s in summaries],
        color="tab:blue",
        capsize=3,
    )
    ax_ret.set_ylabel("return")
    ax_crash.bar(x, [100 * s["crash_rate"] for s in summaries], color="tab:red")
    ax_crash.set_ylabel("crash rate (%)")
    ax_speed.bar(x, [s["speed"] for s in summaries], color="tab:green")
    ax_speed.set_ylabel("mean speed (m/s)")
    for ax in (ax_ret, ax_crash, ax_speed):
        ax.set_xticks(x)
        ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def save_gif(video: torch.Tensor, path: str | Path, fps: int = 5) -> Path:
    """Write a ``(1, T, 3, H, W)`` or ``(T, 3, H, W)`` uint8 video as a GIF (Pillow).

    Example:
        >>> import tempfile, os
        >>> p = save_gif(torch.zeros(2, 3, 8, 8, dtype=torch.uint8), tempfile.mkdtemp() + "/v.gif")
        >>> os.path.getsize(p) > 0
        True
    """
    from PIL import Image

    frames = video.reshape(-1, *video.shape[-3:]).permute(0, 2, 3, 1).numpy()
    images = [Image.fromarray(f) for f in frames]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return path
