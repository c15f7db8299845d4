"""Checkpoints: everything a run needs to continue exactly as if never stopped.

A checkpoint is one dict: the resolved config, the run's :class:`Progress`
(iteration, frames, wall-clock, evaluation history), the policy, the algorithm's part
(:meth:`~torchrl_grpo.training.Algorithm.state_dict`: the loss, whose parameters
include the GRPO reference policy, the optimiser and its step count, the value
network, the reference-sync counter, a lagging tail policy, the replay), the
collector's exact position (:func:`~torchrl_grpo.training.collect.collector_state`) and the
random states of torch, numpy and Python. Files are written atomically (a temporary
file, then a rename), so an interrupt never leaves a half-written ``last.pt``.
:func:`check_resumable` refuses to resume a run with another algorithm or network.

Checkpoints are this project's own files and hold TensorDicts: load them with
:func:`load_checkpoint` (``torch.load(..., weights_only=False)``); do not load
checkpoints from untrusted sources.
"""

from __future__ import annotations

import os
import random
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchrl_grpo.training.retired_keys import SHARED_FIXED

__all__ = [
    "CHECKPOINT_VERSION",
    "Progress",
    "checkpoint_dict",
    "changed_keys",
    "check_resumable",
    "get_rng_state",
    "load_checkpoint",
    "model_changes",
    "save_checkpoint",
    "set_rng_state",
]

#: The layout of a checkpoint's dict; version 1 is every checkpoint written so far. Keys
#: added since are read as optional: ``"threads"`` (2026-12-04).
CHECKPOINT_VERSION = 1

# The algorithm keys of version 1, with the value an algorithm without them writes:
# every checkpoint holds them all, as every checkpoint of version 1 has.
_ALGORITHM_DEFAULTS = {
    "value": None,
    "tail_policy": None,
    "replay": None,
    "ref_sync_counter": None,
    "episode_acc": {},
}


@dataclass
class Progress:
    """How far a run is: its counters and evaluation history (part of its checkpoint).

    Attributes:
        iteration: training iterations done.
        frames: env frames simulated (every branch and trunk step).
        wall_seconds: seconds of training, over every resumed part of the run.
        eval_history: one row per evaluation (``eval_history.jsonl``).

    Example:
        >>> progress = Progress(iteration=3, frames=1200)
        >>> Progress.from_checkpoint(progress.state_dict()) == progress
        True
    """

    iteration: int = 0
    frames: int = 0
    wall_seconds: float = 0.0
    eval_history: list[dict[str, float]] = field(default_factory=list)

    def state_dict(self) -> dict[str, Any]:
        """The counters, as top-level keys of a checkpoint."""
        return {
            "iteration": self.iteration,
            "frames": self.frames,
            "wall_seconds": self.wall_seconds,
            "eval_history": list(self.eval_history),
        }

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> Progress:
        """The progress a checkpoint records."""
        return cls(
            iteration=int(checkpoint["iteration"]),
            frames=int(checkpoint["frames"]),
            wall_seconds=float(checkpoint.get("wall_seconds", 0.0)),
            eval_history=list(checkpoint["eval_history"]),
        )


def checkpoint_dict(
    config: dict[str, Any],
    progress: Progress,
    policy: dict[str, Any],
    algorithm: dict[str, Any],
    collector: dict[str, Any],
) -> dict[str, Any]:
    """A checkpoint: the parts of a run's state, and the random states of this moment.

    It also records torch's thread count (``"threads"``): float sums split across
    threads round differently, so a run continues bit for bit only with the same count.

    Args:
        config: the resolved config.
        progress: the run's counters.
        policy: the policy's ``state_dict()``.
        algorithm: the algorithm's :meth:`~torchrl_grpo.training.Algorithm.state_dict`.
        collector: :func:`~torchrl_grpo.training.collect.collector_state`.

    Example:
        >>> ckpt = checkpoint_dict({"seed": 0}, Progress(iteration=2), {}, {"loss": {}}, {})
        >>> ckpt["version"], ckpt["iteration"], ckpt["replay"], sorted(ckpt["rng"])
        (1, 2, None, ['numpy', 'python', 'torch'])
        >>> ckpt["threads"] == torch.get_num_threads()
        True
    """
    return {
        "version": CHECKPOINT_VERSION,
        "config": config,
        **progress.state_dict(),
        "policy": policy,
        **_ALGORITHM_DEFAULTS,
        **algorithm,
        "collector": collector,
        "rng": get_rng_state(),
        "threads": torch.get_num_threads(),
    }


def get_rng_state() -> dict[str, Any]:
    """Random states of torch, numpy and Python.

    Example:
        >>> state = get_rng_state()
        >>> a = torch.rand(1)
        >>> set_rng_state(state)
        >>> bool(torch.rand(1) == a)
        True
    """
    return {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore :func:`get_rng_state`."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def save_checkpoint(payload: dict[str, Any], path: str | Path) -> Path:
    """Write ``payload`` to ``path`` atomically.

    Example:
        >>> import tempfile
        >>> p = save_checkpoint({"iteration": 3}, tempfile.mkdtemp() + "/last.pt")
        >>> load_checkpoint(p)["iteration"]
        3
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises:
        FileNotFoundError: naming the path.
        ValueError: ``not a valid checkpoint: PATH``, for a truncated file or one that
            is not a checkpoint.

    Example:
        >>> import tempfile
        >>> path = save_checkpoint({"iteration": 3, "policy": {"weight": torch.ones(2)}},
        ...                        tempfile.mkdtemp() + "/last.pt")
        >>> checkpoint = load_checkpoint(path)
        >>> checkpoint["iteration"], checkpoint["policy"]["weight"]
        (3, tensor([1., 1.]))
        >>> try:
        ...     load_checkpoint(path.with_name("missing.pt"))
        ... except FileNotFoundError as err:
        ...     print(str(err).startswith("no checkpoint at"))
        True
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # torch raises OSError, UnpicklingError, RuntimeError, ...
        raise ValueError(f"not a valid checkpoint: {path} ({type(err).__name__})") from err
    if not isinstance(payload, dict):
        raise ValueError(f"not a valid checkpoint: {path} (holds a {type(payload).__name__})")
    return payload


def changed_keys(saved: Any, current: Any, prefix: str = "") -> dict[str, tuple[Any, Any]]:
    """``{dotted key: (saved, current)}`` where two plain config trees differ.

    Only keys both trees hold are compared: a checkpoint written before a key existed
    ran with what is now its default.

    Example:
        >>> changed_keys({"kind": "mlp", "cells": [64], "old": 1}, {"kind": "mlp", "cells": [32]})
        {'cells': ([64], [32])}
    """
    if isinstance(saved, dict) and isinstance(current, dict):
        out: dict[str, tuple[Any, Any]] = {}
        for key in sorted(saved.keys() & current.keys()):
            out |= changed_keys(saved.get(key), current.get(key), f"{prefix}{key}.")
        return out
    return {} if saved == current else {prefix.rstrip("."): (saved, current)}


def model_changes(
    saved: dict[str, Any], current: dict[str, Any], free: Collection[str] = ()
) -> str:
    """The ``model`` keys whose saved weights would not fit: ``model.k=a, not b``, or ``""``.

    The one check of a saved policy against this run's network, for ``resume`` and
    ``init_from`` alike. A changed ``model.prior`` counts, though the parameters keep
    their shapes: they would load silently into a policy with another prior's bonus.

    Args:
        saved: the saved run's ``model`` config (plain).
        current: this run's ``model`` config (plain).
        free: keys that may differ (they weigh or train the same parameters).

    Example:
        >>> model_changes({"kind": "mlp", "crash_aversion": 3.0}, {"kind": "scene",
        ...                "crash_aversion": 5.0}, free={"crash_aversion"})
        "model.kind='mlp', not 'scene'"
    """
    # A key one side lacks holds the value every run now uses (a prior: none).
    saved, current = {**SHARED_FIXED["model"], **saved}, {**SHARED_FIXED["model"], **current}
    return ", ".join(
        f"model.{k}={a!r}, not {b!r}"
        for k, (a, b) in changed_keys(saved, current).items()
        if k not in free
    )


def check_resumable(path: str | Path, saved: dict[str, Any], current: dict[str, Any]) -> None:
    """Refuses to resume a run whose algorithm or network differs from the checkpoint's.

    Args:
        path: the checkpoint, named in the errors.
        saved: the checkpoint's resolved config.
        current: this run's resolved config.

    Raises:
        ValueError: naming the keys that differ.

    Example:
        >>> saved = {"algo": {"name": "ppo"}, "env": {"scenario": "merge-v0"},
        ...          "model": {"kind": "mlp", "prior": None}}
        >>> try:
        ...     check_resumable("last.pt", saved, {**saved, "model": {"kind": "scene"}})
        ... except ValueError as err:
        ...     print(err)
        resume=last.pt was written with another model: model.kind='mlp', not 'scene'
    """
    if saved["algo"]["name"] != current["algo"]["name"]:
        raise ValueError(
            f"resume={path} was written by algo={saved['algo']['name']}, "
            f"not algo={current['algo']['name']}"
        )
    # The simulator's states in the checkpoint (queued roots, live episodes) exist only
    # in the env they were taken in.
    for key in ("scenario", "config"):
        if saved["env"].get(key) != current["env"].get(key):
            raise ValueError(
                f"resume={path} was written on another env: env.{key}="
                f"{saved['env'].get(key)!r}, not {current['env'].get(key)!r}"
            )
    changed = model_changes(saved["model"], current["model"])
    if changed:
        raise ValueError(f"resume={path} was written with another model: {changed}")
