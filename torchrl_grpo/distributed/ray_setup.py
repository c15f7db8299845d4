"""Ray as an optional dependency: a clear error without it, and a small local ``ray.init``."""

from __future__ import annotations

import logging
import os
from types import ModuleType
from typing import Any

logger = logging.getLogger(__name__)

__all__ = ["RAY_EXTRA_HINT", "init_ray", "require_ray"]

RAY_EXTRA_HINT = 'the Ray backend needs Ray: pip install "torchrl_grpo[ray]"'
"""The message of the error raised when the Ray backend is asked for without Ray."""

# Sized for a small shared machine (2 cores, 24 GB): Ray's defaults take 30% of RAM
# for the object store and start the dashboard; branch batches are a few MB each.
DEFAULT_OBJECT_STORE_BYTES = 512 * 1024**2


def require_ray() -> ModuleType:
    """Import and return ``ray``, or raise an ``ImportError`` naming the extra.

    Returns:
        The ``ray`` module.

    Raises:
        ImportError: Ray is not installed (the message says how to install it).

    Example:
        >>> try:
        ...     ray = require_ray()
        ... except ImportError as err:
        ...     assert "torchrl_grpo[ray]" in str(err)
    """
    try:
        import ray
    except ImportError as err:
        raise ImportError(RAY_EXTRA_HINT) from err
    return ray


def init_ray(
    address: str | None = None,
    *,
    num_cpus: float | None = None,
    object_store_memory: int | None = None,
    **kwargs: Any,
) -> bool:
    """Start or join Ray unless it is running already.

    With ``address=None`` (or ``"local"``) a local Ray instance starts, sized for a
    small machine: ``num_cpus`` logical CPUs (default: the machine's cores), an object
    store of ``object_store_memory`` bytes (default 512 MiB) and no dashboard. Any other
    address (``"auto"`` after ``ray start --head`` on a cluster, ``"ray://host:10001"``)
    joins that cluster, whose resources its nodes declared.

    Args:
        address: ``None``/``"local"``, ``"auto"`` or a cluster address.
        num_cpus: logical CPUs of a local instance.
        object_store_memory: object store bytes of a local instance.
        **kwargs: more ``ray.init`` arguments.

    Returns:
        ``True`` when this call started or joined Ray (the caller should shut it down),
        ``False`` when Ray was already initialised.

    Example:
        >>> import ray  # doctest: +SKIP
        >>> init_ray(num_cpus=2, object_store_memory=256 * 1024**2)  # doctest: +SKIP
        True
    """
    ray = require_ray()
    if ray.is_initialized():
        return False
    options: dict[str, Any] = {"logging_level": logging.WARNING}
    if address in (None, "", "local"):
        options["include_dashboard"] = False
        options["num_cpus"] = num_cpus if num_cpus is not None else os.cpu_count()
        options["object_store_memory"] = int(object_store_memory or DEFAULT_OBJECT_STORE_BYTES)
    else:
        # A cluster's resources are declared by its nodes (`ray start --num-cpus ...`).
        options["address"] = address
        if num_cpus is not None or object_store_memory is not None:
            logger.warning("num_cpus / object_store_memory are ignored when joining %s", address)
    options.update(kwargs)
    ray.init(**options)
    logger.info("Ray started: %s", ray.cluster_resources())
    return True
