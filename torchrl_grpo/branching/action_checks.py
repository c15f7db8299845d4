"""The check that a policy's output holds actions the env admits.

Run on the policy's output before an action reaches an env (in the parent, or in a
branch worker that runs its own copy of the policy), so that a bad action fails with
a readable ``ValueError`` instead of an error deep inside a worker's simulator.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite

__all__ = ["check_policy_actions"]


def check_policy_actions(
    td: TensorDictBase, spec: Composite, keys: Sequence, *, per_worker: bool = False
) -> None:
    """Check that ``td`` holds an action for each of ``keys`` that ``spec`` admits.

    Args:
        td: the policy's output.
        spec: the env's full action spec.
        keys: the action keys to check.
        per_worker: the action carries a leading dimension of 1 that the spec (one
            worker's) does not.

    Raises:
        ValueError: an action is missing, has the wrong shape or dtype, or holds
            values outside the spec; the message names the key and the spec.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Categorical
        >>> spec = Composite(action=Categorical(5))
        >>> check_policy_actions(TensorDict(action=torch.tensor(2)), spec, ["action"])
        >>> check_policy_actions(TensorDict(action=torch.tensor(7)), spec, ["action"])
        Traceback (most recent call last):
        ...
        ValueError: the policy's 'action' holds values outside the env's action spec...: [7]
    """
    for key in keys:
        leaf = spec[key]
        expected = (1, *leaf.shape) if per_worker else tuple(leaf.shape)
        action = td.get(key, None)
        if action is None:
            raise ValueError(
                f"the policy wrote no {key!r} entry (its output has "
                f"{sorted(map(str, td.keys(True, True)))}); it must write the env's action"
            )
        if (
            not isinstance(action, torch.Tensor)
            or tuple(action.shape) != expected
            or (action.dtype != leaf.dtype)
        ):
            got = (
                (tuple(action.shape), action.dtype)
                if isinstance(action, torch.Tensor)
                else (type(action).__name__)
            )
            raise ValueError(
                f"the policy's {key!r} does not match the env's action spec: got {got}, "
                f"expected shape {expected} and dtype {leaf.dtype} ({type(leaf).__name__} "
                f"spec{_spec_range(leaf)})"
            )
        if not leaf.is_in(action[0] if per_worker else action):
            raise ValueError(
                f"the policy's {key!r} holds values outside the env's action spec"
                f"{_spec_range(leaf)}: {action.reshape(-1).tolist()[:8]}"
            )


def _spec_range(spec) -> str:
    n = getattr(spec, "n", None)
    if n is not None:
        return f" with {n} actions, indices 0..{n - 1}"
    return ""
