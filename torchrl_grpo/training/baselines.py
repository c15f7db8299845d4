"""The scripted baselines of an evaluation, evaluated once per seed set and cached on disk.

A baseline's episodes depend only on the scenario, its config, the seeds, the episode cap
and the baseline itself, never on the run: a training run, its next run and a sweep all
share one evaluation. The cache is a folder of JSON files, one per baseline and seed set
(``experiment.baseline_cache``, ``outputs/baselines`` by default); a file is keyed by a
hash of everything the episodes depend on, library and highway-env versions included.

The ``lookahead`` baseline is the snapshot planner
(:class:`~torchrl_grpo.branching.LookaheadPolicy`, horizon 8, over the rule policy): the
ceiling that learning from enumerated branches aims at. It simulates about 40 steps per
decision, so it is worth caching.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from torchrl_grpo.branching.lookahead import LookaheadPolicy
from torchrl_grpo.modules.scripted.policy_registry import make_scripted_policy
from torchrl_grpo.training.baseline_cache import (
    LOOKAHEAD_HORIZON,
    cache_key,
    read_cached,
    write_cached,
)
from torchrl_grpo.training.env_builder import make_env, make_layout
from torchrl_grpo.training.evaluation import BASELINE_LABELS, baseline_policy, evaluate
from torchrl_grpo.training.results import EvalResult

__all__ = ["LOOKAHEAD_HORIZON", "cache_key", "evaluate_baselines"]

log = logging.getLogger(__name__)


def _policy(env_cfg: DictConfig, name: str, policy_seed: int) -> tuple[Any, Any] | None:
    """The baseline's policy and the env it drives (``None`` where it does not apply)."""
    if name == "lookahead":
        env = make_env(env_cfg, return_state=True)
        layout = make_layout(env)
        if layout is None or int(env.action_spec.n) != 5:
            return None
        base = make_scripted_policy("rule", layout)
        return LookaheadPolicy(make_env(env_cfg), base, horizon=LOOKAHEAD_HORIZON), env
    env = make_env(env_cfg)
    policy = baseline_policy(name, make_layout(env), int(env.action_spec.n), seed=policy_seed)
    return None if policy is None else (policy, env)


def evaluate_baselines(
    env_cfg: DictConfig,
    names: Sequence[str],
    *,
    episodes: int,
    seed: int,
    cache_dir: str | Path | None = None,
    policy_seed: int = 0,
    workers: int = 1,
    progress: bool = False,
) -> list[EvalResult]:
    """Each baseline of ``names`` on ``episodes`` episodes from ``seed`` on, cached.

    Args:
        env_cfg: the ``env`` config group (scenario, config, ``max_episode_steps``).
        names: baselines: ``random``, ``idle``, ``slower``, ``rule``, ``lookahead``.
        episodes: episodes per baseline.
        seed: the first episode's seed.
        cache_dir: the cache folder; ``None``: evaluate, cache nothing.
        policy_seed: seed of the random baseline's draws.
        workers: processes driving the episodes of one baseline (the same results).
        progress: a tqdm bar over each baseline's episodes (cached ones are not run).

    Returns:
        One result per baseline that applies to the scenario, in the order of ``names``.

    Example:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {},
        ...                         "max_episode_steps": 3})
        >>> cache = tempfile.mkdtemp()
        >>> first = evaluate_baselines(cfg, ["slower"], episodes=2, seed=0, cache_dir=cache)
        >>> again = evaluate_baselines(cfg, ["slower"], episodes=2, seed=0, cache_dir=cache)
        >>> first[0].name, first[0].lengths, again == first
        ('always-SLOWER', [3, 3], True)
    """
    results = []
    for name in names:
        label = "lookahead planner" if name == "lookahead" else BASELINE_LABELS.get(name, name)
        path = None
        if cache_dir is not None:
            path = Path(cache_dir) / cache_key(env_cfg, name, seed, episodes, policy_seed)
            cached = read_cached(path)
            if cached is not None:
                results.append(cached)
                log.info("baseline %s: cached in %s", label, path)
                continue
        built = _policy(env_cfg, name, policy_seed)
        if built is None:
            log.warning("baseline %r does not apply to %s: skipped", name, env_cfg.scenario)
            continue
        policy, env = built
        res, _ = evaluate(
            env,
            policy,
            episodes=episodes,
            seed=seed,
            max_steps=int(env_cfg.get("max_episode_steps", 1000)),
            name=label,
            workers=workers,
            progress=progress,
        )
        results.append(res)
        if path is not None:
            write_cached(path, res)
    return results
