"""GroupCollectorBase: what the local and the Ray group collectors share.

A group collector is a TorchRL collector whose batches are branch groups ``[R, G, T]``.
The base holds the batch shape and the counters (frames, batches, the next group id),
iterates (collect hooks; shut down at the end of the collection and on any error),
loads new policy weights and provides the dunder methods. A subclass implements
:meth:`~GroupCollectorBase._collect` (the next batch) and
:meth:`~GroupCollectorBase._close` (release the envs or actors).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.collectors import BaseCollector

from torchrl_grpo.branching.rollout import RngMode, check_group_args

__all__ = ["GroupCollectorBase"]


class GroupCollectorBase(BaseCollector):
    """Base of the collectors of branch groups, ``[R, G, T]`` batches until ``total_frames``.

    Frames count the valid steps of the yielded batches (``mask.sum()``). The collection
    ends when ``total_frames`` is reached or :meth:`_collect` returns ``None`` (the roots
    ran out); the collector then shuts down, as it does on any error or interrupt
    raised while iterating. Leaving a ``for`` loop with ``break`` keeps it open; use it
    as a context manager to close it on every path.

    A subclass implements :meth:`_collect` and :meth:`_close`, and TorchRL's
    ``set_seed``, ``state_dict`` and ``load_state_dict`` (:meth:`counters_state` is the
    shared part of the state). Until it sets ``self._closed = False``, once it holds what
    :meth:`_close` releases, :meth:`shutdown` does nothing and iterating raises.

    Args:
        policy: the policy (a TensorDict module writing ``"action"``).
        group_size: G >= 2.
        horizon: T >= 1, steps per branch.
        groups_per_batch: R, roots per batch.
        total_frames: stop after this many branch steps (``-1``: never).
        rng: ``"shared"`` or ``"per_branch"`` simulator randomness (checked here).

    Example:
        >>> import torch
        >>> class Zeros(GroupCollectorBase):  # every batch: R groups of G x T valid steps
        ...     def __init__(self, **kwargs):
        ...         super().__init__(None, **kwargs)
        ...         self._closed = False  # it holds something to close from now on
        ...     def _collect(self):
        ...         self._frames += self.frames_per_batch
        ...         shape = [self.groups_per_batch, self.group_size, self.horizon]
        ...         return TensorDict(mask=torch.ones(shape, dtype=torch.bool), batch_size=shape)
        ...     def _close(self, timeout, close_env):
        ...         print("closed")
        ...     def set_seed(self, seed, static_seed=False):
        ...         return seed
        ...     def state_dict(self):
        ...         return self.counters_state()
        ...     def load_state_dict(self, state_dict):
        ...         self.load_counters_state(state_dict)
        >>> collector = Zeros(group_size=2, horizon=3, groups_per_batch=2, total_frames=24)
        >>> [batch.batch_size for batch in collector]
        closed
        [torch.Size([2, 2, 3]), torch.Size([2, 2, 3])]
        >>> collector.frames
        24
    """

    def __init__(
        self,
        policy: TensorDictModuleBase | nn.Module | Callable | None,
        group_size: int,
        horizon: int,
        groups_per_batch: int,
        total_frames: int,
        rng: RngMode = "shared",
    ) -> None:
        super().__init__()
        self._closed = True  # nothing to close until the subclass has opened it
        check_group_args(group_size, horizon, rng)
        if groups_per_batch < 1:
            raise ValueError(f"groups_per_batch must be >= 1, got {groups_per_batch}")
        if total_frames == 0 or total_frames < -1:
            raise ValueError(f"total_frames must be > 0 or -1, got {total_frames}")
        self.policy = policy
        self.group_size = group_size
        self.horizon = horizon
        self.groups_per_batch = groups_per_batch
        self.total_frames = total_frames
        self.frames_per_batch = groups_per_batch * group_size * horizon
        self.requested_frames_per_batch = self.frames_per_batch
        self._frames = 0
        self._batches = 0
        self._next_group_id = 0

    # ------------------------------------------------------------------ subclass hooks
    def _collect(self) -> TensorDictBase | None:
        """The next batch, counted in the counters; ``None`` when the roots ran out."""
        raise NotImplementedError

    def _close(self, timeout: float, close_env: bool) -> None:
        """Release what the collector owns (called once, by :meth:`shutdown`)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ iteration
    @property
    def frames(self) -> int:
        """Branch steps collected so far (valid steps of the yielded batches)."""
        return self._frames

    def __iter__(self) -> Iterator[TensorDictBase]:
        """Iterate over batches; any error or interrupt shuts the collector down."""
        try:
            yield from self.iterator()
        except GeneratorExit:
            # The consumer stopped iterating (``break``): the collector stays usable.
            raise
        except BaseException:
            self.shutdown()
            raise

    def iterator(self) -> Iterator[TensorDictBase]:
        """Yield ``[R, G, T]`` batches until ``total_frames`` (or the roots run out)."""
        if self._closed:
            raise RuntimeError(f"this {type(self).__name__} has been shut down")
        while self.total_frames < 0 or self._frames < self.total_frames:
            if self._pre_collect_hook is not None:
                self._pre_collect_hook()
            batch = self._collect()
            if batch is None:
                break
            if self._post_collect_hook is not None:
                self._post_collect_hook(batch)
            yield batch
        self.shutdown()

    # ------------------------------------------------------------------ TorchRL API
    def update_policy_weights_(
        self,
        policy_or_weights: TensorDictBase | nn.Module | dict | None = None,
        **kwargs: Any,
    ) -> None:
        """Load new weights into the collector's policy.

        The policy lives in this process: it is the trained module itself unless the
        caller passed a copy, and then the trained module (or its weights,
        ``TensorDict.from_module(module)``) goes here. ``None``, or the policy itself,
        is a no-op. (The Ray collector sends its policy's weights to its actors before
        every batch.)
        """
        if kwargs:
            policy_or_weights = kwargs.get("weights", kwargs.get("policy", policy_or_weights))
        if policy_or_weights is None or policy_or_weights is self.policy:
            return
        if not isinstance(self.policy, nn.Module):
            raise TypeError("update_policy_weights_ needs a policy that is an nn.Module")
        if isinstance(policy_or_weights, (nn.Module, TensorDictModuleBase)):
            weights = TensorDict.from_module(policy_or_weights)
        elif isinstance(policy_or_weights, dict):
            weights = TensorDict(policy_or_weights).unflatten_keys(".")
        else:
            weights = policy_or_weights
        weights.data.to_module(self.policy)

    def shutdown(
        self,
        timeout: float | None = None,
        close_env: bool = True,
        raise_on_error: bool = True,
    ) -> None:
        """Close what the collector owns: envs, workers, actors (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._close(10.0 if timeout is None else timeout, close_env)

    def counters_state(self) -> OrderedDict:
        """The counters every group collector checkpoints: frames, batches, next group id.

        Example:
            >>> from torchrl_grpo.branching import GroupCollector
            >>> from torchrl_grpo.envs import HighwayEnv
            >>> from torchrl_grpo.modules import RandomPolicy
            >>> collector = GroupCollector(HighwayEnv("merge-v0"), RandomPolicy(seed=0),
            ...                            group_size=2, horizon=2, groups_per_batch=1)
            >>> dict(collector.counters_state())
            {'frames': 0, 'batches': 0, 'next_group_id': 0}
            >>> collector.shutdown()
        """
        return OrderedDict(
            frames=self._frames, batches=self._batches, next_group_id=self._next_group_id
        )

    def load_counters_state(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`counters_state` (from a subclass's ``state_dict``).

        Example:
            >>> from torchrl_grpo.branching import GroupCollector
            >>> from torchrl_grpo.envs import HighwayEnv
            >>> from torchrl_grpo.modules import RandomPolicy
            >>> collector = GroupCollector(HighwayEnv("merge-v0"), RandomPolicy(seed=0),
            ...                            group_size=2, horizon=2, groups_per_batch=1)
            >>> collector.load_counters_state({"frames": 8, "batches": 2, "next_group_id": 2})
            >>> collector.frames
            8
            >>> collector.shutdown()
        """
        self._frames = int(state_dict["frames"])
        self._batches = int(state_dict["batches"])
        self._next_group_id = int(state_dict["next_group_id"])

    # ------------------------------------------------------------------ dunders
    def __len__(self) -> int:
        raise TypeError("the number of batches depends on where branches end: use total_frames")

    def __bool__(self) -> bool:
        # __len__ raises, and Python would call it for truth tests.
        return True

    def __enter__(self) -> GroupCollectorBase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def __del__(self) -> None:
        # Best effort only: interpreter teardown may already have removed modules.
        try:
            self.shutdown()
        except Exception:  # noqa: S110
            pass

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(group_size={self.group_size}, horizon={self.horizon}, "
            f"groups_per_batch={self.groups_per_batch}, frames={self._frames}/"
            f"{self.total_frames}{self._repr_extra()})"
        )

    def _repr_extra(self) -> str:
        """More ``, name=value`` fields of the subclass for :meth:`__repr__`."""
        return ""
