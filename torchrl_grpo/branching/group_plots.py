"""Draw one branch group: every branch's ego path from the shared start, and its return.

The figure has the two charts of the original prototype, "trajectories from the
same snapshot" (x-y paths coloured by return) and "reward per branch" (a bar per
branch). It is drawn with matplotlib's Agg canvas (no display, no pyplot state)
and returned as a ``(3, H, W)`` uint8 tensor (``wandb.Image(fig.image)``; a
one-frame video for TorchRL loggers: ``logger.log_video(name, fig.video)``), and
optionally written as a PNG.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from tensordict import TensorDictBase

from torchrl_grpo.branching.keys import BRANCH_RETURN, GROUP_ID, MASK

__all__ = ["GroupFigure", "plot_group"]


@dataclass
class GroupFigure:
    """A drawn group.

    Attributes:
        image: ``(3, H, W)`` uint8 RGB image.
        path: where the PNG was written (``None`` when no path was given).

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.branching import branch_rollout, reset_roots
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> data = branch_rollout(env, RandomPolicy(seed=0), reset_roots(env, 1, seed=0), 2, 3)
        >>> fig = plot_group(data, path=tempfile.mkdtemp() + "/group.png", dpi=20)
        >>> fig.image.shape, fig.image.dtype, fig.path.name
        (torch.Size([3, 80, 220]), torch.uint8, 'group.png')
        >>> fig.video.shape  # for logger.log_video(name, fig.video, step=...)
        torch.Size([1, 1, 3, 80, 220])
    """

    image: torch.Tensor
    path: Path | None

    @property
    def video(self) -> torch.Tensor:
        """The image as a one-frame video ``(1, 1, 3, H, W)`` for ``Logger.log_video``."""
        return self.image[None, None]


def plot_group(
    data: TensorDictBase,
    group: int = 0,
    *,
    path: str | Path | None = None,
    title: str | None = None,
    selected: int | None = None,
    dpi: int = 100,
) -> GroupFigure:
    """Draw group ``group`` of a ``[R, G, T]`` branch rollout.

    Args:
        data: branch rollout output (reads ``ego_position``,
            ``("next", "ego_position")``, ``mask``, ``branch_return`` and, if
            present, ``("next", "crashed")``: a crash ends its path with a cross).
        group: the index r of the group along the first dimension.
        path: write the figure there as a PNG.
        title: figure title (default: the group id and root step).
        selected: a branch to highlight (e.g. the one a continuation chose).
        dpi: resolution of the image.

    Returns:
        A :class:`GroupFigure` with the image and the PNG path.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> G, T = 3, 4
        >>> pos = torch.stack([torch.arange(T + 1.0) * 5, torch.zeros(T + 1)], -1)
        >>> pos = pos.expand(1, G, T + 1, 2).clone()
        >>> pos[0, :, :, 1] = torch.arange(G).view(G, 1) * torch.arange(T + 1.0) / T
        >>> data = TensorDict({
        ...     "ego_position": pos[:, :, :-1], ("next", "ego_position"): pos[:, :, 1:],
        ...     "mask": torch.ones(1, G, T, dtype=torch.bool),
        ...     "branch_return": torch.arange(G, dtype=torch.float).view(1, G, 1, 1)
        ...     .expand(1, G, T, 1)}, batch_size=[1, G, T])
        >>> fig = plot_group(data)
        >>> fig.image.shape[0], fig.image.dtype
        (3, torch.uint8)
    """
    group_data = data[group].cpu()  # drawn with numpy
    mask = group_data.get(MASK)
    returns = group_data.get(BRANCH_RETURN)[:, 0].reshape(-1).double().numpy()
    start = group_data.get("ego_position")[:, 0].double().numpy()
    after = group_data.get(("next", "ego_position")).double().numpy()
    n_branches = mask.shape[0]

    fig = Figure(figsize=(11, 4), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax_path, ax_ret = fig.subplots(1, 2, gridspec_kw={"width_ratios": [2, 1]})
    norm = Normalize(vmin=float(returns.min()), vmax=float(returns.max()) + 1e-9)
    cmap = colormaps["viridis"]
    crashed_key = ("next", "crashed")
    crashed = (
        group_data.get(crashed_key).reshape(mask.shape)
        if crashed_key in group_data.keys(True)
        else torch.zeros_like(mask)
    )
    for g in range(n_branches):
        valid = mask[g].numpy()
        xy = np.concatenate([start[g : g + 1], after[g][valid]])
        width = 3.0 if g == selected else 1.5
        color = cmap(norm(returns[g]))
        ax_path.plot(xy[:, 0], xy[:, 1], color=color, lw=width, alpha=0.9)
        # The end of a branch: a cross where the ego crashed, a dot otherwise.
        end_crashed = bool(crashed[g][valid][-1]) if valid.any() else False
        ax_path.plot(
            xy[-1, 0],
            xy[-1, 1],
            "x" if end_crashed else "o",
            color=color,
            ms=8 if end_crashed else 3,
            mew=2,
        )
    ax_path.plot(start[0, 0], start[0, 1], "k*", ms=12, label="shared start")
    ax_path.set_xlabel("x (m)")
    ax_path.set_ylabel("y (m)")
    # highway-env's y axis points down the road's right side, as its renderer draws it.
    ax_path.invert_yaxis()
    ax_path.set_title("trajectories from the same snapshot")
    ax_path.legend(loc="best", fontsize=8)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax_path, label="branch return")

    colors = [cmap(norm(r)) for r in returns]
    bars = ax_ret.bar(np.arange(n_branches), returns, color=colors, edgecolor="k")
    if selected is not None:
        bars[selected].set_linewidth(2.5)
    ax_ret.axhline(float(returns.mean()), color="gray", ls="--", lw=1, label="group mean")
    ax_ret.set_xlabel("branch")
    ax_ret.set_ylabel("return")
    ax_ret.set_xticks(np.arange(n_branches))
    ax_ret.set_title("reward per branch")
    ax_ret.legend(loc="best", fontsize=8)
    if title is None:
        gid = int(group_data.get(GROUP_ID)[0, 0]) if GROUP_ID in group_data.keys() else group
        root_step = group_data.get("root_step")[0, 0] if "root_step" in group_data.keys() else 0
        title = f"group {gid} (root step {int(root_step)}, {n_branches} branches)"
    fig.suptitle(title)
    fig.tight_layout()
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    image = torch.from_numpy(rgba[..., :3].copy()).permute(2, 0, 1).contiguous()
    out_path = None
    if path is not None:
        out_path = Path(path)
        out_path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out_path, format="png")
    return GroupFigure(image=image, path=out_path)
