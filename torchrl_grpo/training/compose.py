"""Composing the run's config: Hydra's compose API, and a resumed run's config.

A resumed run (``resume=PATH``) starts from the config saved in its checkpoint, not from
``conf/``'s defaults of today: without overrides it continues exactly, even after the
defaults changed. The overrides given on the command line apply on top, and every key
they change is logged (:func:`resume_config`).

Example:
    >>> cfg = compose_config(["algo=ppo", "env=merge"])
    >>> str(cfg.algo.name), cfg.env.scenario
    ('ppo', 'merge-v0')
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

from torchrl_grpo.training.checkpoint import changed_keys, check_resumable, load_checkpoint
from torchrl_grpo.training.config import CONF_DIR, register_configs, to_container, typed_config

__all__ = ["compose_config", "resume_config", "user_keys"]

log = logging.getLogger(__name__)


def _compose(overrides: Sequence[str], config_name: str, conf_dir: str | Path) -> DictConfig:
    register_configs()
    if GlobalHydra.instance().is_initialized():
        # Inside a ``@hydra.main`` app (scripts/train.py): its search path is ``conf/``.
        return compose(config_name, overrides=list(overrides))
    with initialize_config_dir(str(Path(conf_dir).resolve()), version_base=None):
        return compose(config_name, overrides=list(overrides))


def compose_config(
    overrides: Sequence[str] = (), config_name: str = "config", conf_dir: str | Path = CONF_DIR
) -> DictConfig:
    """Compose ``conf/<config_name>.yaml`` with ``overrides``, as ``scripts/train.py`` does.

    Registers the schemas first (:func:`~torchrl_grpo.training.register_configs`). With
    ``resume=PATH`` among the overrides, the config is the checkpoint's with the other
    overrides on top (:func:`resume_config`).

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = compose_config(["algo=ppo", "env=merge"])
        >>> str(cfg.algo.name), cfg.env.scenario, OmegaConf.get_type(cfg.algo).__name__
        ('ppo', 'merge-v0', 'PPOConfig')
    """
    cfg = _compose(overrides, config_name, conf_dir)
    if config_name == "config" and cfg.get("resume"):
        cfg = resume_config(cfg, overrides, conf_dir=conf_dir)
    return cfg


def user_keys(
    overrides: Sequence[str], config_name: str = "config", conf_dir: str | Path = CONF_DIR
) -> dict[str, Any]:
    """The config keys that ``overrides`` set away from the defaults, with their values.

    Group choices (``algo=ppo``, ``experiment=smoke``) count through the keys they change;
    a key named on its own counts even where it asks for the default value (a resume
    must apply ``algo.group_fit_coeff=0.0`` over a checkpoint's 2.0). ``resume`` and
    Hydra's own keys are left out.

    Example:
        >>> user_keys(["algo.epochs=3", "seed=1", "resume=last.pt", "algo.group_size=5"])
        {'algo.epochs': 3, 'seed': 1, 'algo.group_size': 5}
    """
    kept = [o for o in overrides if o.lstrip("+~").split("=")[0] not in ("resume", "hydra")]
    kept = [o for o in kept if not o.lstrip("+~").startswith("hydra.")]
    default = to_container(_compose([], config_name, conf_dir))
    chosen = to_container(_compose(kept, config_name, conf_dir))
    keys = {key: new for key, (_, new) in _leaf_changes(default, chosen).items()}
    for override in kept:
        name = override.lstrip("+~").split("=")[0]
        node: Any = chosen
        for part in name.split("."):
            node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
        if node is not _ABSENT and not isinstance(node, dict):
            keys.setdefault(name, node)
    return keys


# A key an override names that the composed config does not hold (``~key``, deleted).
_ABSENT = object()


def _leaf_changes(old: Any, new: Any, prefix: str = "") -> dict[str, tuple[Any, Any]]:
    """Like :func:`changed_keys`, with keys that only ``new`` has."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: dict[str, tuple[Any, Any]] = {}
        for key in new:
            out |= _leaf_changes(old.get(key), new[key], f"{prefix}{key}.")
        return out
    return {} if old == new else {prefix.rstrip("."): (old, new)}


def resume_config(
    cfg: DictConfig, overrides: Sequence[str], conf_dir: str | Path = CONF_DIR
) -> DictConfig:
    """A resumed run's config: the checkpoint's, with the user's ``overrides`` on top.

    Every key whose value differs from the checkpoint's is logged.

    Args:
        cfg: the config composed from ``overrides`` (its ``resume`` names the checkpoint).
        overrides: the command line's overrides.
        conf_dir: the config folder the overrides were composed in.

    Raises:
        ValueError: the checkpoint cannot be read (see
            :func:`~torchrl_grpo.training.load_checkpoint`), or the overrides ask for
            another algorithm, env or network (see
            ``torchrl_grpo.training.checkpoint.check_resumable``).

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training.checkpoint import save_checkpoint
        >>> saved = to_container(compose_config(["algo.group_size=4"]))
        >>> path = save_checkpoint({"config": saved}, tempfile.mkdtemp() + "/last.pt")
        >>> cfg = compose_config([f"resume={path}", "algo.epochs=1"])
        >>> cfg.algo.group_size, cfg.algo.epochs, cfg.resume == str(path)
        (4, 1, True)
    """
    path = str(cfg.resume)
    saved = to_container(typed_config(load_checkpoint(path)["config"]))
    requested = copy.deepcopy(saved)
    for key, value in user_keys(overrides, conf_dir=conf_dir).items():
        *parents, leaf = key.split(".")
        node = requested
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    requested["resume"] = path
    # Before typing: another algorithm's keys do not fit the checkpoint's schema.
    check_resumable(path, saved, requested)
    for key, (old, new) in changed_keys(saved, requested).items():
        if key != "resume":
            log.warning("resume=%s: %s=%r (the checkpoint's run had %r)", path, key, new, old)
    return typed_config(requested)
