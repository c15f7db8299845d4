"""A first-in first-out store of labelled states whose checkpoint holds only what is kept."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

__all__ = ["LabelledStates"]


class LabelledStates:
    """The last ``capacity`` rows extended into it, in a ring.

    TorchRL's ``LazyTensorStorage`` saves its whole preallocated capacity; a run that
    keeps a million states but has labelled a tenth of them saves the tenth here.

    Args:
        capacity: the most rows kept (``>= 1``); the oldest go first.

    Example:
        >>> from tensordict import TensorDict
        >>> kept = LabelledStates(3)
        >>> kept.extend(TensorDict(x=torch.arange(4.0), batch_size=[4]))
        >>> len(kept), sorted(kept.rows["x"].tolist())  # 0.0 went first
        (3, [1.0, 2.0, 3.0])
        >>> again = LabelledStates(3)
        >>> again.load_state_dict(kept.state_dict())
        >>> again.extend(TensorDict(x=torch.tensor([9.0]), batch_size=[1]))
        >>> sorted(again.rows["x"].tolist())  # 1.0, the oldest, went
        [2.0, 3.0, 9.0]
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self._store: TensorDictBase | None = None
        self._filled = 0
        self._cursor = 0

    def __len__(self) -> int:
        return self._filled

    @property
    def rows(self) -> TensorDictBase:
        """The kept rows (in storage order, not in the order they came)."""
        if self._store is None:
            raise ValueError("no state is kept yet")
        return self._store[: self._filled]

    def extend(self, rows: TensorDictBase) -> None:
        """Keeps ``rows`` (a flat batch), dropping the oldest kept ones beyond capacity."""
        rows = rows[-self.capacity :]
        n = rows.shape[0]
        if self._store is None:
            self._store = rows[:1].expand(self.capacity).clone()
        at = (self._cursor + torch.arange(n)) % self.capacity
        self._store[at] = rows
        self._cursor = (self._cursor + n) % self.capacity
        self._filled = min(self._filled + n, self.capacity)

    def state_dict(self) -> dict[str, Any]:
        """The kept rows and the ring's write position."""
        rows = None if self._store is None else self.rows.clone()
        return {"rows": rows, "cursor": self._cursor, "capacity": self.capacity}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores :meth:`state_dict`; the capacity must be the same.

        Raises:
            ValueError: a state saved with another capacity (naming both).
        """
        if int(state["capacity"]) != self.capacity:
            raise ValueError(
                f"the checkpoint kept up to {state['capacity']} states, this run "
                f"{self.capacity}: resume with the same algo.replay_frames"
            )
        self._store, self._filled, self._cursor = None, 0, 0
        if state["rows"] is not None:
            self.extend(state["rows"])
            self._cursor = int(state["cursor"])
