"""Keys the config schemas no longer have: the values runs now use, and old configs' migration.

The recommended recipes fix what used to be knobs (issue #40): a run composes at most
50 keys. Each retired key is one of:

* **fixed**: every run of an algorithm uses one value (:data:`SHARED_FIXED`, and
  :meth:`~torchrl_grpo.training.Algorithm.fixed_settings` per algorithm, e.g. GRPO with
  branching uses ``algo.roots=trunk``). The code still reads the key: :func:`with_fixed`
  fills it in the config the trainer runs, so that the research variants keep one code
  path. Those variants' keys are the config of the experimental ``algo=grpo_lab``
  (``torchrl_grpo.experimental``), which takes them from the command line;
* **dropped**: it changed nothing a run computes (``experiment.name``,
  ``logger.tags``, the unused keys of another algorithm or network kind).

A config written before (a checkpoint's, a run's ``config.yaml``) is read through
:func:`migrate`: a fixed key holding its fixed value and a dropped key go; a fixed key
holding another value makes the run an ``algo=grpo_lab`` run, whose schemas have it, or
is refused with an error that names the key and what took its place.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

__all__ = [
    "DROPPED",
    "LATER_RETIRED",
    "OLD_DEFAULTS",
    "RENAMED",
    "SHARED_FIXED",
    "LabRequired",
    "migrate",
    "renamed",
    "with_fixed",
    "written_before_retirement",
]

#: The value every run now uses, for keys no algorithm's schema has.
SHARED_FIXED: dict[str, dict[str, Any]] = {
    "rollout": {"mp_start_method": "fork"},
    "optim": {"eps": 1e-8, "weight_decay": 0.0},
    "model": {"prior": None, "prior_weight": 2.0, "ensemble": 1, "bagging": False},
}

#: Keys that changed nothing a run computes, or that now follow from another key.
DROPPED: dict[str, frozenset[str]] = {
    "env": frozenset({"name"}),
    "experiment": frozenset({"name", "transfer_gap", "progress_bar", "plot_every"}),
    "logger": frozenset({"mode", "project", "group", "tags", "group_plots", "video"}),
}

#: What a config written before the keys retired meant by leaving one out: the old
#: schemas' defaults (a v1 checkpoint has no ``rollout.live_trunks``; it ran without),
#: where they are not :data:`SHARED_FIXED`'s values.
OLD_DEFAULTS: dict[str, dict[str, Any]] = {
    "algo": {
        "roots": "trunk",
        "select": "best",
        "returns": "branch",
        "bootstrap": "batch_mean",
        "crash_penalty": 0.0,
        "baseline": "mean",
        "scale_rewards": "group",
        "gamma": 1.0,
        "dual_clip": None,
        "kl_estimator": "k3",
        "aggregation": "dapo",
        "ref_model_sync_steps": 64,
        "ref_model_mixup_alpha": 1.0,
        "explore_steps": None,
        "first_action": "sample",
        "action_weights": "uniform",
        "tail_sync_batches": None,
        "trunk": "sample",
        "group_fit_temperature": 0.1,
        "group_fit_weighting": "uniform",
        "group_fit_loss": "cross_entropy",
        "crash_head_coeff": 1.0,
        "crash_label": "branch",
        "crash_head_tail": False,
        "max_minibatches": None,
    },
    "rollout": {
        "live_trunks": False,
        "stagger_trunks": False,
        "full_horizon_roots": False,
        "first_root_step": 0,
    },
}

#: Keys retired after the others (#42: the group fit's weight, which each GRPO variant
#: now fixes): a config holding only these was written with today's other keys, and
#: :data:`OLD_DEFAULTS` does not apply to it.
LATER_RETIRED: dict[str, frozenset[str]] = {"algo": frozenset({"group_fit_coeff"})}

#: Keys renamed: ``{group: {old: new}}``.
RENAMED: dict[str, dict[str, str]] = {
    "algo": {
        "distill_coeff": "group_fit_coeff",
        "distill_loss": "group_fit_loss",
        "distill_temperature": "group_fit_temperature",
        "distill_weighting": "group_fit_weighting",
    }
}


def renamed(group: str, node: Mapping[str, Any]) -> dict[str, Any]:
    """A group's plain config with its renamed keys (:data:`RENAMED`) under today's names.

    Example:
        >>> renamed("algo", {"name": "grpo_branch", "distill_coeff": 1.0})
        {'name': 'grpo_branch', 'group_fit_coeff': 1.0}
    """
    out = dict(node)
    for old, new in RENAMED.get(group, {}).items():
        if old in out:
            out.setdefault(new, out.pop(old))
    return out


class LabRequired(ValueError):
    """A config holds values of retired keys that only ``algo=grpo_lab`` runs."""


def with_fixed(container: dict[str, Any], fixed: Mapping[str, Mapping[str, Any]]) -> dict:
    """``container`` with every key of ``fixed`` it lacks set to its fixed value.

    Example:
        >>> with_fixed({"algo": {"name": "x", "roots": "reset"}},
        ...            {"algo": {"roots": "trunk", "gamma": 1.0}})
        {'algo': {'name': 'x', 'roots': 'reset', 'gamma': 1.0}}
    """
    out = copy.deepcopy(container)
    for group, values in fixed.items():
        node = out.get(group)
        if isinstance(node, dict):
            for key, value in values.items():
                node.setdefault(key, value)
    return out


def migrate(
    container: Mapping[str, Any],
    fixed: Mapping[str, Mapping[str, Any]],
    schema_keys: Mapping[str, frozenset[str]],
) -> dict[str, Any]:
    """An older config in today's keys: renamed, fixed values and dropped keys removed.

    Args:
        container: the plain config (a checkpoint's).
        fixed: ``{group: {key: value}}`` that its algorithm now fixes (shared ones included).
        schema_keys: ``{group: keys}`` of today's schema of each group.

    Returns:
        The config without the retired keys.

    Raises:
        LabRequired: a retired key holds another value than the fixed one, naming it.

    Example:
        >>> old = {"algo": {"name": "grpo_branch", "roots": "trunk", "distill_coeff": 1.0},
        ...        "experiment": {"name": "smoke", "total_frames": 20}}
        >>> keys = {"algo": frozenset({"name", "group_fit_coeff"}),
        ...         "experiment": frozenset({"total_frames"})}
        >>> migrate(old, {"algo": {"roots": "trunk"}}, keys)["algo"]
        {'name': 'grpo_branch', 'group_fit_coeff': 1.0}
        >>> try:
        ...     migrate({"algo": {"name": "grpo_branch", "roots": "continue"}},
        ...             {"algo": {"roots": "trunk"}}, keys)
        ... except LabRequired as err:
        ...     print(err)
        algo.roots='continue' (grpo_branch now fixes 'trunk'): a key of algo=grpo_lab
    """
    out = copy.deepcopy(dict(container))
    differing: list[str] = []
    name = (out.get("algo") or {}).get("name")
    for group, keys in schema_keys.items():
        node = out.get(group)
        if not isinstance(node, dict):
            continue
        node = out[group] = renamed(group, node)
        group_fixed = fixed.get(group, {})
        defaults = OLD_DEFAULTS.get(group, {}) if _holds_retired(group, node, keys) else {}
        for key in sorted(set(node) | set(defaults)):
            if key in keys:
                continue
            value = node.pop(key, defaults.get(key))
            if key in group_fixed and _differs(value, group_fixed[key]):
                differing.append(f"{group}.{key}={value!r} ({name} now fixes {group_fixed[key]!r})")
    if differing:
        raise LabRequired(", ".join(differing) + ": a key of algo=grpo_lab")
    return out


def written_before_retirement(
    container: Mapping[str, Any], schema_keys: Mapping[str, frozenset[str]]
) -> bool:
    """Whether ``container`` was written before the keys retired (it holds one of them).

    Its missing keys then meant :data:`OLD_DEFAULTS`' values; a config written after
    meant the values its algorithm fixes. Only :data:`LATER_RETIRED` keys do not count.

    Example:
        >>> keys = {"algo": frozenset({"name"})}
        >>> written_before_retirement({"algo": {"name": "grpo_branch", "roots": "trunk"}}, keys)
        True
        >>> written_before_retirement({"algo": {"name": "grpo_branch", "group_fit_coeff": 1}}, keys)
        False
    """
    return any(
        isinstance(container.get(group), Mapping) and _holds_retired(group, container[group], keys)
        for group, keys in schema_keys.items()
    )


def _holds_retired(group: str, node: Mapping[str, Any], keys: frozenset[str]) -> bool:
    # A config that holds none of a group's retired keys was written with today's.
    return bool(node.keys() - keys - LATER_RETIRED.get(group, frozenset()))


def _differs(value: Any, fixed: Any) -> bool:
    if isinstance(value, int | float) and isinstance(fixed, int | float):
        return float(value) != float(fixed)
    return str(value) != str(fixed) if value is not None and fixed is not None else value != fixed
