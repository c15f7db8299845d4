"""Checks of the relations between config keys that types alone cannot express.

The shared groups are checked here; the ``algo`` group by its algorithm
(:meth:`~torchrl_grpo.training.Algorithm.check_config`).
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from torchrl_grpo.training.algos.registry import algorithm_for, with_fixed_settings
from torchrl_grpo.training.group_schemas import collects_on_ray

__all__ = ["check_config"]


def check_config(cfg: DictConfig) -> None:
    """Checks the relations between keys that types alone cannot express.

    The shared groups' here; the ``algo`` group's by its algorithm
    (:meth:`~torchrl_grpo.training.Algorithm.check_config`).

    Raises:
        ValueError: naming the offending key.

    Example:
        >>> from torchrl_grpo.training import Config
        >>> from torchrl_grpo.training.group_schemas import GroupRolloutConfig
        >>> cfg = OmegaConf.structured(Config(rollout=GroupRolloutConfig(horizon=0)))
        >>> try:
        ...     check_config(cfg)
        ... except ValueError as err:
        ...     print(err)
        rollout.horizon must be >= 1, got 0
    """
    algo = _group(cfg, "algo")
    if algo is not None and "name" in algo and not OmegaConf.is_missing(algo, "name"):
        # The algorithm's checks read the settings its recipe fixes as well.
        cfg = with_fixed_settings(cfg)
    for key, low in _LOWER_BOUNDS.items():
        group, name = key.split(".")
        node = _group(cfg, group)
        if node is None or name not in node or OmegaConf.is_missing(node, name):
            continue
        value = node[name]
        if value is not None and value < low:
            raise ValueError(f"{key} must be >= {low}, got {value}")
    rollout = _group(cfg, "rollout")
    if rollout is not None:
        _check_rollout(rollout)
    experiment = _group(cfg, "experiment")
    if experiment is not None:
        _check_eval_seeds(experiment)
    algo = _group(cfg, "algo")
    if algo is not None:
        algorithm_for(algo).check_config(cfg)


# Lower bounds of the keys that have one.
_LOWER_BOUNDS = {
    "rollout.horizon": 1,
    "rollout.decision_interval": 1,
    "rollout.groups_per_batch": 1,
    "rollout.frames_per_batch": 1,
    "rollout.num_workers": 1,
    "experiment.total_frames": 1,
    "env.max_episode_steps": 1,
    "experiment.eval_every": 0,
    "experiment.eval_episodes": 0,
    "experiment.final_eval_episodes": 0,
    "experiment.checkpoint_every": 0,
    "algo.epochs": 1,
    "algo.minibatch_size": 1,
}


def _group(cfg: DictConfig, group: str) -> DictConfig | None:
    if OmegaConf.is_missing(cfg, group):
        return None
    return cfg.get(group)


def _check_rollout(rollout: DictConfig) -> None:
    """The ``rollout`` keys; the Ray settings (``rollout=ray``)."""
    backend = str(rollout.backend)
    on_ray = collects_on_ray(rollout)
    if backend == "ray":
        raise ValueError(
            "rollout.backend=ray: choose rollout=ray, GRPO's groups on Ray actors "
            "(rollout.backend is then how each actor runs its env workers; docs/distributed.md)"
        )
    if backend == "single" and rollout.num_workers != 1:
        where = " (workers per Ray actor)" if on_ray else ""
        raise ValueError(
            f"rollout.num_workers{where} must be 1 with rollout.backend=single, "
            f"got {rollout.num_workers}"
        )
    if rollout.get("stagger_trunks") and not rollout.get("live_trunks"):
        raise ValueError(
            "rollout.stagger_trunks=true spreads the episodes of live trunks: set "
            "rollout.live_trunks=true too (with algo.roots=trunk)"
        )
    if not on_ray:
        return
    ray = rollout.ray
    if ray.num_actors < 1:
        raise ValueError(f"rollout.ray.num_actors must be >= 1, got {ray.num_actors}")
    if ray.num_actors > rollout.groups_per_batch:
        raise ValueError(
            f"rollout.ray.num_actors ({ray.num_actors}) must be <= rollout.groups_per_batch "
            f"({rollout.groups_per_batch}): every actor collects at least one group"
        )
    if ray.num_cpus_per_actor <= 0:
        raise ValueError(
            f"rollout.ray.num_cpus_per_actor must be > 0, got {ray.num_cpus_per_actor}"
        )


def _check_eval_seeds(exp: DictConfig) -> None:
    """The periodic evaluation's seeds and the final one's are disjoint sets."""
    keys = ("eval_seed", "eval_episodes", "final_eval_seed", "final_eval_episodes")
    if any(k not in exp or OmegaConf.is_missing(exp, k) for k in keys):
        return
    periodic = range(int(exp.eval_seed), int(exp.eval_seed) + int(exp.eval_episodes))
    final = range(int(exp.final_eval_seed), int(exp.final_eval_seed) + int(exp.final_eval_episodes))
    shared = range(max(periodic.start, final.start), min(periodic.stop, final.stop))
    if len(periodic) and len(final) and len(shared):
        raise ValueError(
            f"experiment.eval_seed and experiment.final_eval_seed overlap: the periodic "
            f"evaluation's seeds {periodic.start}..{periodic.stop - 1} and the final one's "
            f"{final.start}..{final.stop - 1} share {shared.start}..{shared.stop - 1}; the "
            "final evaluation must drive episodes the run never selected on"
        )
