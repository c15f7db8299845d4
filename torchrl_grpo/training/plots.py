"""All the plots of a run: the learning curve, the policies compared, a GIF of an episode.

Figures are drawn with Matplotlib's object API on an Agg canvas (no display, no global
state), then written to PNG; videos are written as GIFs with Pillow. The branch-group
plots are :func:`torchrl_grpo.branching.plot_group`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from torchrl_grpo.training.results import EvalResult

__all__ = ["plot_comparison", "plot_learning_curve", "save_gif"]


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
