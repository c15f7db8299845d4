"""What every branch engine fills in and returns: ``[N * H]`` rows and a :class:`BranchRun`.

A rollout of N branches of at most H steps writes each step's rows by index into
preallocated ``[N * H]`` leaves (:class:`StepRows`; no per-step tensordict clone,
stack or cat), and returns them as ``[N, H]`` data with the mask of the steps taken,
each branch's length, whether it ended and, when kept, its final state
(:class:`RolloutRows`, :class:`BranchRun`). The engines that fill them:
:mod:`~torchrl_grpo.branching.worker_branches` (whole branches in the workers) and
:mod:`~torchrl_grpo.branching.lockstep` (the policy in this process);
:mod:`~torchrl_grpo.branching.batched_worlds` returns a :class:`BranchRun` too.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from torchrl_grpo.branching.keys import STATE

__all__ = ["BranchRun", "KeepStates", "Policy", "RolloutRows", "StepRows"]

KeepStates = Literal["none", "final", "all"]
Policy = Callable[[TensorDictBase], TensorDictBase | None]


@dataclass
class BranchRun:
    """What a branch engine returns for N branches of at most H steps.

    Attributes:
        data: ``[N, H]`` per-step data, zeros on the steps after a branch ended.
        mask: ``[N, H]`` bool, ``True`` on the steps the branch took.
        lengths: ``[N]`` int64, the number of steps each branch took.
        ended: ``[N]`` bool, the env reported ``done`` on the branch's last step.
        final_states: ``[N]`` states after each branch's last step (``keep != "none"``).
    """

    data: TensorDict
    mask: torch.Tensor
    lengths: torch.Tensor
    ended: torch.Tensor
    final_states: TensorDictBase | None


class StepRows:
    """Preallocated ``[size, ...]`` leaves, filled by index from ``[W, ...]`` tensordicts.

    The first tensordict written fixes the keys, shapes and dtypes (its leaves minus
    ``skip``); rows never written stay zero.
    """

    def __init__(self, size: int, skip: Iterable[NestedKey] = ()) -> None:
        self.size = size
        self.skip = {k if isinstance(k, tuple) else (k,) for k in skip}
        self.keys: list[NestedKey] = []
        self.leaves: list[torch.Tensor] = []
        self.views: list[np.ndarray] = []

    def _allocate(self, td: TensorDictBase) -> None:
        for key, value in td.items(True, True):
            path = key if isinstance(key, tuple) else (key,)
            if any(path[: len(s)] == s for s in self.skip):
                continue
            self.keys.append(key)
            self.leaves.append(value.new_zeros((self.size, *value.shape[1:])))

    def write(self, where: torch.Tensor, td: TensorDictBase, rows: torch.Tensor | None) -> None:
        """``self[where[i]] = td[rows[i]]`` for every leaf (``rows=None``: all rows of ``td``)."""
        if not self.keys:
            self._allocate(td)
        for key, leaf in zip(self.keys, self.leaves, strict=True):
            value = td.get(key)
            leaf.index_copy_(0, where, value if rows is None else value[rows])

    def write_block(self, start: int, block: Mapping[tuple, np.ndarray]) -> None:
        """``self[start : start + T] = block``: ``[T, ...]`` numpy arrays by tuple key.

        The first call fixes the keys (those of ``block`` minus ``skip``), shapes and dtypes.

        Example:
            >>> rows = StepRows(6)
            >>> rows.write_block(3, {("a",): np.ones((2, 4), np.float32)})
            >>> rows.tensordict(2, 3)["a"].sum(-1).tolist()
            [[0.0, 0.0, 0.0], [4.0, 4.0, 0.0]]
        """
        if not self.keys:
            self._allocate_arrays({k: v.shape[1:] for k, v in block.items()}, block)
        if not self.views:
            self.views = [leaf.numpy() for leaf in self.leaves]
        for key, view in zip(self.keys, self.views, strict=True):
            value = block[key]
            view[start : start + len(value)] = value

    def _allocate_arrays(
        self, shapes: Mapping[tuple, tuple], like: Mapping[tuple, np.ndarray]
    ) -> None:
        for key, shape in shapes.items():
            if any(key[: len(s)] == s for s in self.skip):
                continue
            self.keys.append(key)
            self.leaves.append(torch.from_numpy(np.zeros((self.size, *shape), like[key].dtype)))

    def tensordict(self, *shape: int) -> TensorDict:
        """The leaves as a tensordict of batch size ``shape`` (``prod(shape) == size``)."""
        out = TensorDict(batch_size=shape)
        for key, leaf in zip(self.keys, self.leaves, strict=True):
            out.set(key, leaf.view(*shape, *leaf.shape[1:]))
        return out


class RolloutRows:
    """What a rollout of N branches of at most H steps fills in, and its :class:`BranchRun`.

    The ``[N * H]`` rows of the policy's input and output (``root_rows``, minus what a
    step adds) and of each step's ``"next"`` (``next_rows``), with ``keep="all"`` the
    states before and after each step (``state_rows``); the ``[N * H]`` mask of the
    steps taken, each branch's length and whether it ended, and with ``keep != "none"``
    each branch's final state (its start state until it is written). The worker-slot
    engines (lock-step, whole branches) write these and return :meth:`result`.

    Args:
        states: ``[N]`` start states of the branches.
        horizon: H.
        keep: which states the rollout keeps.
    """

    def __init__(self, states: TensorDictBase, horizon: int, keep: KeepStates) -> None:
        self.n_branches, self.horizon = states.shape[0], horizon
        size = self.n_branches * horizon
        self.lengths = torch.zeros(self.n_branches, dtype=torch.long)
        self.ended = torch.zeros(self.n_branches, dtype=torch.bool)
        self.mask = torch.zeros(size, dtype=torch.bool)
        self.final = states.clone() if keep != "none" else None
        self.root_rows = StepRows(size, skip=(STATE, "next", "_step"))
        self.next_rows = StepRows(size, skip=(STATE,))
        self.state_rows = (StepRows(size), StepRows(size)) if keep == "all" else None

    def final_state_views(self, keys: Iterable[NestedKey]) -> list[tuple[NestedKey, np.ndarray]]:
        """Numpy views of the final states' leaves ``keys`` (none when no state is kept)."""
        if self.final is None:
            return []
        return [(key, self.final.get(key).numpy()) for key in keys]

    def result(self) -> BranchRun:
        """The rollout's :class:`BranchRun`: the rows as ``[N, H]`` leaves."""
        n, h = self.n_branches, self.horizon
        data = self.root_rows.tensordict(n, h)
        data.set("next", self.next_rows.tensordict(n, h))
        if self.state_rows is not None:
            data.set(STATE, self.state_rows[0].tensordict(n, h))
            data.set(("next", STATE), self.state_rows[1].tensordict(n, h))
        return BranchRun(
            data=data,
            mask=self.mask.view(n, h),
            lengths=self.lengths,
            ended=self.ended,
            final_states=self.final,
        )
