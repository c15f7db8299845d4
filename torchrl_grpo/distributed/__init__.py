"""Branch groups on a Ray cluster: :class:`RayGroupCollector` and its actors.

Ray is optional (``pip install "torchrl_grpo[ray]"``): this package imports without
it, and building a :class:`RayGroupCollector` without it raises an ``ImportError``
naming the extra. See ``docs/distributed.md``.
"""

from torchrl_grpo.distributed.actor_pool import split_groups
from torchrl_grpo.distributed.collector import RayGroupCollector
from torchrl_grpo.distributed.ray_setup import RAY_EXTRA_HINT, init_ray, require_ray
from torchrl_grpo.distributed.worker import GroupResult, GroupWorker, WorkerSnapshot, actor_seed

__all__ = [
    "RAY_EXTRA_HINT",
    "GroupResult",
    "GroupWorker",
    "RayGroupCollector",
    "WorkerSnapshot",
    "actor_seed",
    "init_ray",
    "require_ray",
    "split_groups",
]
