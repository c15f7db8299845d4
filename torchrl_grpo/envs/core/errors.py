"""Errors raised when a simulator state cannot be captured or restored.

Every error subclasses :class:`SnapshotError` (itself a :class:`ValueError`), so a
caller can catch the family at once. They are raised *before* the environment is
modified: after one of them the environment is exactly as it was.
"""

from __future__ import annotations


class SnapshotError(ValueError):
    """Base class of every snapshot / restore failure.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv, SnapshotEnv, states_equal
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> before = env.get_state()
        >>> try:  # a CartPole state cannot be restored into a highway env
        ...     env.set_state(SnapshotEnv("CartPole-v1", seed=0).get_state())
        ... except SnapshotError as err:  # catches every error of this module
        ...     print(type(err).__name__, isinstance(err, ValueError))
        StateMismatchError True
        >>> states_equal(env.get_state(), before)  # the env is left as it was
        True
    """


class StateMismatchError(SnapshotError):
    """The state was captured from another scenario, config or codec layout.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> padded = HighwayEnv("merge-v0", seed=0, max_vehicles=40).get_state()
        >>> try:  # same scenario, but padded to another number of vehicles
        ...     env.set_state(padded)
        ... except StateMismatchError as err:
        ...     print("another state layout" in str(err), isinstance(err, SnapshotError))
        True True
    """


class StateCorruptedError(SnapshotError):
    """The state is truncated, has wrong shapes or dtypes, or holds invalid values.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> try:
        ...     env.set_state(env.get_state().exclude("sim"))
        ... except StateCorruptedError as err:
        ...     print(err)
        the state is truncated: it has no 'sim' part
    """


class StateCapacityError(SnapshotError):
    """The simulator holds more items than the fixed-size state can pad to.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = HighwayEnv("merge-v0", seed=0, max_vehicles=2)  # merge-v0 starts with 5
        >>> try:
        ...     env.get_state()
        ... except StateCapacityError as err:
        ...     print(str(err).split(";")[0])
        the road holds 5 vehicles and 1 objects
    """


class UnknownFieldError(SnapshotError):
    """A simulator object carries an attribute the codec does not know how to store.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> vehicle = env.gym_env.unwrapped.road.vehicles[1]
        >>> vehicle.my_field = 1.0  # an attribute highway-env does not have
        >>> try:
        ...     env.get_state()
        ... except UnknownFieldError as err:
        ...     print(str(err).split(" is not")[0])
        IDMVehicle.my_field
        >>> del vehicle.my_field
        >>> env.get_state().batch_size  # capturing works again
        torch.Size([])
    """
