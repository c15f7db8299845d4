"""The outcomes of evaluation episodes: one :class:`EvalResult` per policy, and their table."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = ["EvalResult", "compare_paired", "format_table", "paired_difference", "paired_verdicts"]


@dataclass
class EvalResult:
    """Per-episode outcomes of one policy.

    Attributes:
        name: the policy's label.
        returns: undiscounted return of each episode.
        crashed: whether the ego crashed.
        lengths: steps of each episode.
        speeds: mean ego speed of each episode (m/s).
        seeds: the episodes' seeds.

    :func:`~torchrl_grpo.training.evaluate` fills one, episode after episode.

    Example:
        >>> result = EvalResult("always-SLOWER")
        >>> for seed, ret in enumerate([20.5, 21.5]):
        ...     result.returns.append(ret)
        ...     result.crashed.append(False)
        ...     result.lengths.append(30)
        ...     result.speeds.append(20.0)
        ...     result.seeds.append(seed)
        >>> result.name, result.episodes, result.summary()["return"]
        ('always-SLOWER', 2, 21.0)
    """

    name: str
    returns: list[float] = field(default_factory=list)
    crashed: list[bool] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)
    speeds: list[float] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)

    @property
    def episodes(self) -> int:
        """Number of episodes."""
        return len(self.returns)

    def summary(self) -> dict[str, float]:
        """Means (and the return's std and standard error) over episodes.

        Example:
            >>> r = EvalResult("x", [1.0, 3.0], [False, True], [2, 4], [20.0, 30.0], [0, 1])
            >>> r.summary()["crash_rate"], r.summary()["return"]
            (0.5, 2.0)
        """
        returns = np.asarray(self.returns, dtype=np.float64)
        n = max(len(returns), 1)
        std = float(returns.std(ddof=1)) if len(returns) > 1 else 0.0
        return {
            "return": float(returns.mean()) if len(returns) else math.nan,
            "return_std": std,
            "return_sem": std / math.sqrt(n),
            "crash_rate": float(np.mean(self.crashed)) if self.crashed else math.nan,
            "speed": float(np.mean(self.speeds)) if self.speeds else math.nan,
            "length": float(np.mean(self.lengths)) if self.lengths else math.nan,
            "episodes": float(len(returns)),
        }

    def to_dict(self) -> dict:
        """Plain data for JSON."""
        return {**asdict(self), "summary": self.summary()}


def format_table(results: Sequence[EvalResult]) -> str:
    """A Markdown table: return (mean ± std), crash rate, mean speed, episode length.

    Example:
        >>> r = EvalResult("slower", [20.0, 22.0], [False, False], [30, 30], [20.0, 20.0])
        >>> print(format_table([r]).splitlines()[2])
        | slower | 21.00 ± 1.41 | 0.0% | 20.0 | 30.0 | 2 |
    """
    lines = [
        "| policy | return | crash rate | speed (m/s) | length (steps) | episodes |",
        "|---|---|---|---|---|---|",
    ]
    for res in results:
        s = res.summary()
        lines.append(
            f"| {res.name} | {s['return']:.2f} ± {s['return_std']:.2f} | "
            f"{100 * s['crash_rate']:.1f}% | {s['speed']:.1f} | {s['length']:.1f} | "
            f"{int(s['episodes'])} |"
        )
    return "\n".join(lines)


def paired_difference(policy: EvalResult, baseline: EvalResult) -> tuple[np.ndarray, float, bool]:
    """The per-episode return differences, their standard error, and whether ``policy`` beats.

    "Beats" is paired on the same seeds: a mean return higher by more than two standard
    errors of the per-episode difference, and a crash rate no higher.

    Raises:
        ValueError: the results are not of the same seeds.

    Example:
        >>> a = EvalResult("a", [22.0, 23.0, 24.0], [False] * 3, [30] * 3, [25.0] * 3, [0, 1, 2])
        >>> b = EvalResult("b", [20.0, 20.5, 21.0], [False] * 3, [30] * 3, [20.0] * 3, [0, 1, 2])
        >>> diff, sem, beats = paired_difference(a, b)
        >>> diff.tolist(), round(sem, 2), beats
        ([2.0, 2.5, 3.0], 0.29, True)
    """
    if policy.seeds != baseline.seeds:
        raise ValueError(f"{policy.name} and {baseline.name} drove other episodes")
    diff = np.asarray(policy.returns, np.float64) - np.asarray(baseline.returns, np.float64)
    n = len(diff)
    sem = float(diff.std(ddof=1) / math.sqrt(n)) if n > 1 else math.inf
    beats = float(diff.mean()) > 2 * sem and np.mean(policy.crashed) <= np.mean(baseline.crashed)
    return diff, sem, bool(beats)


def compare_paired(policy: EvalResult, baseline: EvalResult) -> str:
    """Whether ``policy`` beats ``baseline`` on the same episodes, as one line.

    The figures and the verdict of :func:`paired_difference`.

    Raises:
        ValueError: the results are not of the same seeds.

    Example:
        >>> a = EvalResult("a", [22.0, 23.0, 24.0], [False] * 3, [30] * 3, [25.0] * 3, [0, 1, 2])
        >>> b = EvalResult("b", [20.0, 20.5, 21.0], [False] * 3, [30] * 3, [20.0] * 3, [0, 1, 2])
        >>> print(compare_paired(a, b))
        a vs b: return +2.50 ± 0.29 (paired, 3 episodes), crash rate 0.0% vs 0.0%: beats b
    """
    diff, sem, beats = paired_difference(policy, baseline)
    crash_a, crash_b = float(np.mean(policy.crashed)), float(np.mean(baseline.crashed))
    return (
        f"{policy.name} vs {baseline.name}: return {diff.mean():+.2f} ± {sem:.2f} "
        f"(paired, {len(diff)} episodes), crash rate {100 * crash_a:.1f}% vs {100 * crash_b:.1f}%: "
        + (f"beats {baseline.name}" if beats else f"does not beat {baseline.name}")
    )


def paired_verdicts(policy: EvalResult, others: Sequence[EvalResult]) -> str:
    """:func:`compare_paired` of ``policy`` against each of ``others``, one per line.

    Example:
        >>> a = EvalResult("a", [22.0, 23.0], [False] * 2, [30] * 2, [25.0] * 2, [0, 1])
        >>> b = EvalResult("b", [20.0, 21.0], [True, False], [9, 30], [20.0] * 2, [0, 1])
        >>> print(paired_verdicts(a, [b, b]).splitlines()[1])
        a vs b: return +2.00 ± 0.00 (paired, 2 episodes), crash rate 0.0% vs 50.0%: beats b
    """
    return "\n".join(compare_paired(policy, other) for other in others)
