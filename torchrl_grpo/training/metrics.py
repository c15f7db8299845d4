"""Metric helpers of the training loop: phase timing, names of loss outputs, progress bar.

The metric namespaces are listed in :mod:`~torchrl_grpo.training.logging_builder`.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch
from tensordict import TensorDictBase

from torchrl_grpo.branching.keys import BRANCH_RETURN, MASK

__all__ = ["PhaseTimer", "group_metrics", "metric_name", "progress_bar", "progress_postfix"]

# The metrics the progress bar shows, by their short names.
_POSTFIX = {
    "eval/return": "eval",
    "eval/crash_rate": "crash",
    "collect/group_return_mean": "group_ret",
    "collect/episode_return": "ep_ret",
    "train/loss_objective": "loss",
    "time/fps": "fps",
}


class PhaseTimer:
    """Wall-clock seconds per phase, accumulated until :meth:`pop`.

    Example:
        >>> timer = PhaseTimer()
        >>> with timer("collect"):
        ...     pass
        >>> sorted(timer.pop())
        ['time/collect']
    """

    def __init__(self) -> None:
        self._totals: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        """Time the ``with`` block as ``phase``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self._totals[phase] += time.perf_counter() - start

    def pop(self) -> dict[str, float]:
        """The accumulated times as ``time/<phase>`` metrics, then reset."""
        out = {f"time/{k}": v for k, v in self._totals.items()}
        self._totals.clear()
        return out


def metric_name(key: str) -> str:
    """The metric of a loss output: every term and diagnostic under ``train/``, by its key.

    Example:
        >>> metric_name("loss_objective"), metric_name("clip_fraction")
        ('train/loss_objective', 'train/clip_fraction')
    """
    return f"train/{key}"


def progress_bar(enabled: bool, total: int, initial: int) -> Any | None:
    """A tqdm bar over ``total`` frames starting at ``initial`` (``None`` when disabled).

    Example:
        >>> progress_bar(False, 100, 0) is None
        True
    """
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=min(initial, total), unit="frames", dynamic_ncols=True)


def progress_postfix(metrics: dict[str, float]) -> dict[str, str]:
    """The few metrics the progress bar shows, by short name.

    Example:
        >>> progress_postfix({"eval/return": 21.456, "train/lr": 1e-3})
        {'eval': '21.5'}
    """
    return {short: f"{metrics[k]:.3g}" for k, short in _POSTFIX.items() if k in metrics}


def group_metrics(batch: TensorDictBase) -> dict[str, float]:
    """Statistics of a ``[R, G, T]`` batch of branch groups (``collect/``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> mask = torch.tensor([[[True, True], [True, False]]])  # 1 group of 2 branches
        >>> batch = TensorDict({
        ...     "mask": mask,
        ...     "branch_return": torch.tensor([[2.0, 0.5]]).view(1, 2, 1, 1).expand(1, 2, 2, 1),
        ...     ("next", "reward"): torch.tensor([[[1.0, 1.0], [0.5, 0.0]]]).unsqueeze(-1),
        ...     ("next", "crashed"): torch.tensor([[[False, False], [True, False]]]).unsqueeze(-1),
        ...     ("next", "speed"): torch.full((1, 2, 2, 1), 20.0),
        ... }, batch_size=[1, 2, 2])
        >>> m = group_metrics(batch)
        >>> m["collect/group_return_mean"], m["collect/group_crash_spread"], m["collect/reward"]
        (1.25, 1.0, 0.8333333134651184)
    """
    mask = batch.get(MASK)
    returns = batch.get(BRANCH_RETURN)[:, :, 0, 0].double()
    lengths = mask.sum(-1).double()
    crashed = (batch.get(("next", "crashed")).reshape(mask.shape) & mask).any(-1)
    speed = batch.get(("next", "speed")).reshape(mask.shape)[mask]
    std = returns.std(1) if returns.shape[1] > 1 else torch.zeros(returns.shape[0])
    reward = batch.get(("next", "reward")).reshape(mask.shape)[mask]
    return {
        "collect/group_return_mean": float(returns.mean()),
        "collect/group_return_std": float(std.mean()),
        "collect/group_zero_std_fraction": float((std == 0).double().mean()),
        "collect/group_best_minus_mean": float((returns.max(1).values - returns.mean(1)).mean()),
        "collect/group_crash_spread": float((crashed.any(1) & ~crashed.all(1)).double().mean()),
        "collect/branch_return": float(returns.mean()),
        "collect/branch_length": float(lengths.mean()),
        "collect/crash_rate": float(crashed.double().mean()),
        "collect/speed": float(speed.float().mean()) if speed.numel() else math.nan,
        "collect/reward": float(reward.float().mean()),
    }
