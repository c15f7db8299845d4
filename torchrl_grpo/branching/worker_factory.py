"""The constructor of branch workers: a worker env with its branch runner attached.

A :class:`~torchrl_grpo.branching.BranchParallelEnv` wraps each worker constructor in a
:class:`BranchWorkerFactory`, so that every worker env carries the runner its parent
sends whole branches to through TorchRL's generic attribute call: ``env.branch_runs``
(a :class:`~torchrl_grpo.branching.branch_runner.BranchRunner`, which steps branches
with the worker's own copy of the policy).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torchrl.envs import EnvBase

from torchrl_grpo.branching.branch_runner import BranchRunner

__all__ = ["BranchWorkerFactory"]


class BranchWorkerFactory:
    """Builds a worker env with a :class:`BranchRunner` attached.

    Args:
        make: the worker constructor (what ``ParallelEnv`` would be given).

    Example:
        >>> import functools
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = BranchWorkerFactory(functools.partial(HighwayEnv, "merge-v0"))()
        >>> isinstance(env.branch_runs, BranchRunner)
        True
    """

    def __init__(self, make: Callable[..., EnvBase]) -> None:
        self.make = make

    def __eq__(self, other: object) -> bool:
        # ParallelEnv tells one constructor for all workers by comparing them.
        return isinstance(other, BranchWorkerFactory) and other.make == self.make

    def __hash__(self) -> int:
        return hash(self.make)

    def __call__(self, **kwargs: Any) -> EnvBase:
        """Build the worker env (``make(**kwargs)``) with its runner attached."""
        env = self.make(**kwargs)
        env.branch_runs = BranchRunner(env)
        return env
