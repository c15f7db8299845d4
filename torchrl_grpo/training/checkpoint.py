"""Checkpoints: everything a run needs to continue exactly as if never stopped.

A checkpoint holds the policy, the loss (its parameters include the GRPO reference
policy), the value network, the optimiser, the reference-sync counter, the
collector's counters and root queue (or, for PPO, the workers' simulator states
mid-episode), the trainer's counters and the random states of torch, numpy and
Python. Files are written atomically (a temporary file, then a rename), so an
interrupt never leaves a half-written ``last.pt``.

Checkpoints are this project's own files and hold TensorDicts: load them with
:func:`load_checkpoint` (``torch.load(..., weights_only=False)``); do not load
checkpoints from untrusted sources.
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["get_rng_state", "load_checkpoint", "save_checkpoint", "set_rng_state"]


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
    return torch.load(path, map_location="cpu", weights_only=False)
