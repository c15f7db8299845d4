"""The CartPole tutorial's two pictures: the learning curve and one group's branches.

Drawn with matplotlib's Agg backend (no display, no pyplot state) by
``tutorials/cartpole_grpo.py``, section 4.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import matplotlib.colors
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

ENV_ID = "CartPole-v1"
MAX_RETURN = 500  # CartPole-v1's TimeLimit: 500 steps, reward 1 per step
THETA_LIMIT = 12 * 2 * math.pi / 360  # the pole falls (episode ends) beyond 12 degrees
X_LIMIT = 2.4  # the cart leaves the track beyond 2.4


def plot_curve(path: Path, curve, rule_mean: float, reached: dict | None, group_size: int) -> None:
    """Greedy evaluation return vs training env frames, the rule and 500 as lines."""
    frames = [f for f, _ in curve]
    means = [float(r.mean()) for _, r in curve]
    fig = Figure(figsize=(7, 4.2))
    FigureCanvasAgg(fig)  # matplotlib's Agg backend: no display, no pyplot state
    ax = fig.subplots()
    ax.fill_between(
        frames, [float(r.min()) for _, r in curve], [float(r.max()) for _, r in curve],
        color="C0", alpha=0.2, label="min-max over eval episodes",
    )  # fmt: skip
    ax.plot(frames, means, "o-", color="C0", ms=3, label="GRPO policy (greedy), mean")
    ax.axhline(rule_mean, color="C2", lw=3, alpha=0.6, label=f"rule policy ({rule_mean:.0f})")
    ax.axhline(MAX_RETURN, color="k", ls=":", lw=1, label=f"maximum return ({MAX_RETURN})")
    if reached is not None:
        ax.axvline(reached["frames"], color="C3", lw=1, alpha=0.6)
        ax.annotate(
            f"{MAX_RETURN} on every eval episode\n{reached['frames']} frames, "
            f"{reached['seconds']:.0f} s",
            (reached["frames"], MAX_RETURN * 0.12), ha="right", fontsize=8, color="C3",
        )  # fmt: skip
    ax.set_xlabel("training env frames (branch steps)")
    ax.set_ylabel("episode return")
    ax.set_ylim(0, MAX_RETURN * 1.08)
    ax.set_title(f"GRPO on {ENV_ID}: groups of {group_size} rollouts from one snapshot")
    ax.legend(loc="center right", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def plot_group(path: Path, group) -> None:
    """Pole angle and cart position of every branch of one group, coloured by return.

    ``group``: the tutorial's ``GroupRecord`` (observations, mask, returns, terminated,
    iteration).
    """
    fig = Figure(figsize=(12, 4.2))
    FigureCanvasAgg(fig)
    ax_theta, ax_x, ax_ret = fig.subplots(1, 3, gridspec_kw={"width_ratios": [3, 3, 1.4]})
    returns = group.returns
    norm = matplotlib.colors.Normalize(
        float(returns.min()), max(float(returns.max()), float(returns.min()) + 1)
    )
    cmap = matplotlib.colormaps["viridis"]
    for g in range(returns.shape[0]):
        n = int(group.mask[g].sum())
        obs = group.observation[g, :n]
        t = torch.arange(n)
        color = cmap(norm(float(returns[g])))
        for ax, col in ((ax_theta, 2), (ax_x, 0)):
            ax.plot(t, obs[:, col], color=color, lw=1.2)
            if bool(group.terminated[g]):
                ax.plot(t[-1], obs[-1, col], "x", color=color, ms=7, mew=2)
    for ax, limit, label in ((ax_theta, THETA_LIMIT, "pole angle [rad]"), (ax_x, X_LIMIT, "x")):
        ax.axhline(limit, color="grey", ls=":", lw=1)
        ax.axhline(-limit, color="grey", ls=":", lw=1)
        ax.set_xlabel("step from the shared snapshot")
        ax.set_ylabel(label)
    ax_theta.set_title("pole angle per branch (x: the episode ended)")
    ax_x.set_title("cart position per branch")
    colors = [cmap(norm(float(r))) for r in returns]
    ax_ret.bar(range(len(returns)), returns.tolist(), color=colors)
    ax_ret.axhline(float(returns.mean()), color="k", ls="--", lw=1, label="group mean")
    ax_ret.set_xticks(range(len(returns)))
    ax_ret.set_xlabel("branch")
    ax_ret.set_ylabel("return")
    ax_ret.set_ylim(0, float(returns.max()) * 1.25)
    ax_ret.legend(fontsize=8, loc="upper right")
    fig.suptitle(
        f"one group (training iteration {group.iteration}): {len(returns)} branches of the "
        "sampling policy from bitwise the same CartPole state\n"
        "a step's advantage: its discounted reward-to-go against the group's at the same step",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
