"""Errors raised when a simulator state cannot be captured or restored.

Every error subclasses :class:`SnapshotError` (itself a :class:`ValueError`), so a
caller can catch the family at once. They are raised *before* the environment is
modified: after one of them the environment is exactly as it was.
"""

from __future__ import annotations


class SnapshotError(ValueError):
    """Base class of every snapshot / restore failure."""


class StateMismatchError(SnapshotError):
    """The state was captured from another scenario, config or codec layout."""


class StateCorruptedError(SnapshotError):
    """The state is truncated, has wrong shapes or dtypes, or holds invalid values."""


class StateCapacityError(SnapshotError):
    """The simulator holds more items than the fixed-size state can pad to."""


class UnknownFieldError(SnapshotError):
    """A simulator object carries an attribute the codec does not know how to store."""
