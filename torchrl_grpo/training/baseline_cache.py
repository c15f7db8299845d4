"""The cache of the baselines' episodes: one JSON file per baseline and seed set.

A file is keyed by a hash of everything the episodes depend on (scenario, config, seeds,
episode cap, the baseline, library and highway-env versions);
:func:`~torchrl_grpo.training.evaluate_baselines` fills it, and ``scripts/evaluate.py``
reads it back for the learning curve without evaluating anything.
"""

from __future__ import annotations

import hashlib
import json
from importlib.metadata import version
from pathlib import Path

from omegaconf import DictConfig

from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.results import EvalResult

__all__ = ["LOOKAHEAD_HORIZON", "cache_key", "read_cached", "write_cached"]

#: Steps per branch of the ``lookahead`` baseline.
LOOKAHEAD_HORIZON = 8
# Bump when what a cached file means changes.
_CACHE_VERSION = 1


def cache_key(env_cfg: DictConfig, name: str, seed: int, episodes: int, policy_seed: int) -> str:
    """The file name a baseline's episodes are cached under.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {},
        ...                         "max_episode_steps": 40})
        >>> key = cache_key(cfg, "slower", 10_000, 30, 0)
        >>> key.startswith("highway-fast-v0_slower_10000x30_"), key == cache_key(
        ...     cfg, "slower", 10_000, 30, 0), key == cache_key(cfg, "slower", 10_001, 30, 0)
        (True, True, False)
    """
    what = {
        "scenario": str(env_cfg.scenario),
        "config": env_overrides(env_cfg),
        "max_steps": int(env_cfg.get("max_episode_steps", 1000)),
        "name": name,
        "seed": seed,
        "episodes": episodes,
        # Only the random baseline draws from its seed.
        "policy_seed": policy_seed if name == "random" else 0,
        "lookahead_horizon": LOOKAHEAD_HORIZON if name == "lookahead" else 0,
        "versions": [_CACHE_VERSION, version("torchrl_grpo"), version("highway-env")],
    }
    digest = hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()
    return f"{env_cfg.scenario}_{name}_{seed}x{episodes}_{digest[:16]}.json"


def read_cached(path: str | Path) -> EvalResult | None:
    """The result cached at ``path``, or ``None`` when there is none.

    Example:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "slower.json"
        >>> read_cached(path) is None
        True
        >>> write_cached(path, EvalResult("slower", [1.0], [False], [3], [20.0], [0]))
        >>> read_cached(path).returns
        [1.0]
    """
    path = Path(path)
    if not path.is_file():
        return None
    stored = json.loads(path.read_text())
    stored.pop("summary", None)
    return EvalResult(**stored)


def write_cached(path: str | Path, result: EvalResult) -> None:
    """Write ``result`` at ``path`` atomically (a reader never sees half a file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result.to_dict()))
    tmp.replace(path)
