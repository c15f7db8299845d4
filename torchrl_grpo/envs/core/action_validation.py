"""The check that an action fits the env's action spec, run before a step changes anything.

Every env of the package runs :func:`check_action` at the top of its ``_step`` (unless
built with ``check_actions=False``): an action out of range, of the wrong dtype or of
the wrong shape raises :class:`InvalidActionError` in the calling process, naming the
env, the offending rows and values, and the spec, and the env is left as it was.
Without it, an off-by-one in a policy trains silently on wrong data (the tensor
simulator stepped action 7 as if it were a valid one) or fails deep inside the
simulator (highway-env's ``KeyError: 7``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from torchrl.data import Bounded, Categorical, OneHot, TensorSpec

__all__ = ["InvalidActionError", "check_action", "describe_spec", "gym_action"]

# Rows and values an error message lists at most.
_SHOWN = 8


class InvalidActionError(ValueError):
    """An action outside the env's action spec: out of range, wrong dtype or wrong shape.

    Raised before the env changes: after one, the env steps as if the call never was.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> env = TensorHighwayEnv(num_envs=2, seed=0)
        >>> _ = env.reset()
        >>> try:
        ...     env.step(TensorDict(action=torch.tensor([1, 7]), batch_size=[2]))
        ... except InvalidActionError as err:
        ...     print(str(err).split(" in ")[1])
        rows [1]: values [7]
    """


def describe_spec(spec: TensorSpec) -> str:
    """A short description of an action spec for error messages.

    Example:
        >>> describe_spec(Categorical(5, shape=(4,)))
        'Categorical(n=5: integers 0..4, shape=(4,), dtype=torch.int64)'
    """
    shape, dtype = tuple(spec.shape), spec.dtype
    if isinstance(spec, Categorical):
        n = spec.space.n
        return f"Categorical(n={n}: integers 0..{n - 1}, shape={shape}, dtype={dtype})"
    if isinstance(spec, OneHot):
        n = spec.space.n
        return f"OneHot(n={n}: one-hot vectors of {n}, shape={shape}, dtype={dtype})"
    if isinstance(spec, Bounded):
        low, high = spec.space.low, spec.space.high
        if low.numel() <= _SHOWN:
            bounds = f"low={low.reshape(-1).tolist()}, high={high.reshape(-1).tolist()}"
        else:
            bounds = f"low>={low.min().item()}, high<={high.max().item()}"
        return f"{type(spec).__name__}({bounds}, shape={shape}, dtype={dtype})"
    return f"{type(spec).__name__}(shape={shape}, dtype={dtype})"


def check_action(
    action: object,
    spec: TensorSpec,
    env: str,
    *,
    batch_dims: int = 0,
    rows: torch.Tensor | None = None,
) -> None:
    """Refuse an action that ``spec`` does not admit, naming ``env``, the rows and the values.

    Categorical actions must be integers in ``0..n-1``, one-hot actions integer or bool
    vectors with exactly one 1, bounded (continuous) actions floats within the bounds
    (NaN is outside), all of exactly the spec's shape. Other specs are checked with
    their own ``is_in``. One vectorised comparison over the batch; a batched check
    reads one bool back to the host (a device sync on a GPU).

    Args:
        action: the ``"action"`` entry the env received.
        spec: the env's action spec (batch dimensions included).
        env: the env, as the error names it (e.g. ``"HighwayEnv('merge-v0')"``).
        batch_dims: leading dimensions of ``spec`` that are the env's batch; the error
            lists the offending indices along them as rows.
        rows: the ``"_step"`` mask (batch-shaped) of a partial step: rows that do not
            step are not checked.

    Raises:
        InvalidActionError: the action is not a tensor, or has the wrong shape or dtype,
            or holds values outside the spec.

    Example:
        >>> check_action(torch.tensor(4), Categorical(5), "my env")
        >>> try:
        ...     check_action(torch.tensor(1.5), Categorical(5), "my env")
        ... except InvalidActionError as err:
        ...     print(str(err).split(", but")[0])
        my env: actions of dtype torch.float32 (1.5)
    """
    if not isinstance(action, torch.Tensor):
        raise InvalidActionError(
            f"{env}: the action is a {type(action).__name__}, not a tensor; the action spec is "
            f"{describe_spec(spec)}"
        )
    if action.shape != spec.shape:
        raise InvalidActionError(
            f"{env}: actions of shape {tuple(action.shape)} ({_head(action)}), but the action "
            f"spec is {describe_spec(spec)}"
        )
    floating = action.dtype.is_floating_point or action.dtype.is_complex
    if isinstance(spec, (Categorical, OneHot)):
        kind = "integers" if isinstance(spec, Categorical) else "integers or bools"
        # A bool is no index unless the spec's own dtype is bool.
        as_bool = action.dtype == torch.bool and spec.dtype != torch.bool
        wrong_dtype = floating or (as_bool and isinstance(spec, Categorical))
    elif isinstance(spec, Bounded):
        kind, wrong_dtype = "floats", not action.dtype.is_floating_point
    else:
        kind, wrong_dtype = "", False
    if wrong_dtype:
        raise InvalidActionError(
            f"{env}: actions of dtype {action.dtype} ({_head(action)}), but the action spec "
            f"{describe_spec(spec)} takes {kind}"
        )
    bad = _outside(action, spec, batch_dims)
    if bad is None:
        return
    if rows is not None:
        bad = bad & rows.reshape(bad.shape)
    if not bool(bad.any()):
        return
    spec_text = describe_spec(spec)
    if batch_dims == 0:
        raise InvalidActionError(
            f"{env}: action {_head(action)} is outside the action spec {spec_text}"
        )
    found = bad.nonzero()
    shown = found[:_SHOWN]
    values = action[tuple(shown.unbind(-1))].tolist()
    index = (shown.squeeze(-1) if batch_dims == 1 else shown).tolist()
    more = f" (the first {_SHOWN} of {len(found)})" if len(found) > _SHOWN else ""
    raise InvalidActionError(
        f"{env}: actions outside the action spec {spec_text} in rows {index}{more}: values {values}"
    )


def _outside(action: torch.Tensor, spec: TensorSpec, batch_dims: int) -> torch.Tensor | None:
    """A bool tensor of the batch's shape: which rows hold an action outside ``spec``."""
    if isinstance(spec, Categorical):
        if action.ndim == 0:  # one env: no tensor ops, a Python comparison
            return None if 0 <= int(action) < spec.space.n else torch.ones((), dtype=torch.bool)
        bad = (action < 0) | (action >= spec.space.n)
    elif isinstance(spec, OneHot):
        bad = action.sum(-1) != 1
        if action.dtype != torch.bool:
            bad = bad | ((action != 0) & (action != 1)).any(-1)
    elif isinstance(spec, Bounded):
        low, high = spec.space.low, spec.space.high
        bad = ~((action >= low) & (action <= high))  # NaN fails both comparisons
    else:
        if spec.is_in(action):
            return None
        bad = torch.ones(spec.shape[:batch_dims], dtype=torch.bool, device=action.device)
    # Reduce the spec's own dimensions: one flag per row of the batch.
    while bad.ndim > batch_dims:
        bad = bad.any(-1)
    return bad


def _head(action: torch.Tensor) -> list | float | int | bool:
    """The first values of ``action``, for a message."""
    if action.ndim == 0:
        return action.item()
    return action.reshape(-1)[:_SHOWN].tolist()


def gym_action(action: torch.Tensor, space: gym.Space, categorical: bool = True) -> Any:
    """The action as ``space`` takes it: an int for ``Discrete``, else a numpy array.

    Args:
        action: the env's ``"action"`` entry (an index, or a one-hot vector when
            ``categorical`` is ``False``).
        space: the gymnasium env's action space.
        categorical: discrete actions are indices (``False``: one-hot vectors).

    Example:
        >>> gym_action(torch.tensor([0, 1, 0]), gym.spaces.Discrete(3), categorical=False)
        1
    """
    if isinstance(space, gym.spaces.Discrete):
        if not categorical:
            action = action.argmax(-1)
        return int(action)
    return action.detach().cpu().numpy()
