"""The registry of algorithms by ``algo.name``, and the config a run of one executes.

:func:`register_algorithm` adds a subclass of
:class:`~torchrl_grpo.training.Algorithm`; :func:`algorithm_for` finds it from an
``algo`` config (Hydra's ConfigStore gets its schema from
:func:`~torchrl_grpo.training.register_configs`).
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from torchrl_grpo.training.algos.base import Algorithm

__all__ = ["ALGORITHMS", "algorithm_for", "register_algorithm", "with_fixed_settings"]

#: The registered algorithms by ``algo.name`` (:func:`register_algorithm` fills it).
ALGORITHMS: dict[str, type[Algorithm]] = {}


def with_fixed_settings(cfg: DictConfig) -> DictConfig:
    """The config a run executes: ``cfg`` plus the values its algorithm fixes.

    See :meth:`Algorithm.with_fixed_settings`.

    Example:
        >>> from torchrl_grpo.training import compose_config
        >>> cfg = compose_config([])
        >>> "roots" in cfg.algo, with_fixed_settings(cfg).algo.roots
        (False, 'trunk')
    """
    return algorithm_for(cfg.algo).with_fixed_settings(cfg)


def register_algorithm(cls: type[Algorithm]) -> type[Algorithm]:
    """Registers an :class:`Algorithm` under its ``names`` (a class decorator).

    Call :func:`~torchrl_grpo.training.register_configs` after it, so that Hydra knows
    its schema. Registering the same class again is a no-op.

    Raises:
        ValueError: the class has no names or config name, or a name is taken.

    Example:
        >>> from dataclasses import dataclass
        >>> from torchrl_grpo.training import PPO, PPOConfig
        >>> from torchrl_grpo.training.algos.registry import ALGORITHMS
        >>> @dataclass
        ... class MyPPOConfig(PPOConfig):
        ...     name: str = "my_ppo"
        >>> @register_algorithm
        ... class MyPPO(PPO):
        ...     names = ("my_ppo",)
        ...     config_class = MyPPOConfig
        ...     config_name = "base_my_ppo"
        >>> ALGORITHMS["my_ppo"] is MyPPO
        True
        >>> del ALGORITHMS["my_ppo"]  # leave the registry as it was
    """
    if not cls.names or not cls.config_name:
        raise ValueError(f"{cls.__name__} needs names and a config_name to be registered")
    for name in cls.names:
        taken = ALGORITHMS.get(name)
        if taken is not None and _qualified(taken) != _qualified(cls):
            raise ValueError(f"algo.name={name!r} is taken by {_qualified(taken)}")
    for name in cls.names:
        ALGORITHMS[name] = cls
    return cls


def _qualified(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def algorithm_for(algo_cfg: Any) -> type[Algorithm]:
    """The registered algorithm of an ``algo`` config: by its name, else by its schema.

    Raises:
        ValueError: no registered algorithm has that name (or schema).

    Example:
        >>> algorithm_for(OmegaConf.create({"name": "ppo"})).__name__
        'PPO'
    """
    name = None
    if isinstance(algo_cfg, DictConfig):
        if "name" in algo_cfg and not OmegaConf.is_missing(algo_cfg, "name"):
            name = str(algo_cfg.name)
        schema = OmegaConf.get_type(algo_cfg)
    else:
        name = algo_cfg.get("name")
        schema = type(algo_cfg)
    if name is None:
        found = {cls for cls in ALGORITHMS.values() if cls.config_class is schema}
        if len(found) == 1:
            return found.pop()
    elif name in ALGORITHMS:
        return ALGORITHMS[name]
    raise ValueError(
        f"algo.name={name!r} is not a registered algorithm "
        f"({', '.join(sorted(ALGORITHMS))}); see register_algorithm"
    )
