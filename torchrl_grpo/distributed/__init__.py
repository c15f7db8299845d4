"""Branch groups on a Ray cluster: :class:`RayGroupCollector` and its actors.

Ray is optional (``pip install "torchrl_grpo[ray]"``): this package imports without
it, and building a :class:`RayGroupCollector` without it raises an ``ImportError``
naming the extra. See ``docs/distributed.md``.
"""

from torchrl_grpo.distributed.ray_collector import RayGroupCollector
from torchrl_grpo.distributed.ray_setup import init_ray

__all__ = [
    "RayGroupCollector",
    "init_ray",
]
