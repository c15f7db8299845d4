"""The env-level part of a highway-env state: everything that is not a road object.

Time and counters, the generator, which vehicles are controlled, acted on and
observed, the action and observation types' own state (a continuous action's last
command, the Kinematics ``features_range``, grayscale frames), and lane-keeping's
extras (its env-level lanes and growing trajectory, stored by
:mod:`.lane_keeping_fields`). The rules a restore checks these entries against are in
:mod:`.env_checks`. Built by :class:`~torchrl_grpo.envs.highway.highway_codec.HighwayStateCodec`
when it
binds to an env.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from highway_env.envs.common.action import ContinuousAction
from highway_env.envs.common.observation import (
    GrayscaleObservation,
    KinematicObservation,
    KinematicsGoalObservation,
)
from torchrl.data import Unbounded

from torchrl_grpo.envs.core.errors import (
    StateCapacityError,
    StateCorruptedError,
    UnknownFieldError,
)
from torchrl_grpo.envs.core.gym_state import (
    RNG_WORDS,
    decode_rng,
    encode_rng,
    restore_wrappers,
    time_limit,
)
from torchrl_grpo.envs.highway.env_checks import (
    check_class_parameters,
    check_features_range,
    check_magnitude,
    check_observed_goal,
    vehicle_in_slot,
)
from torchrl_grpo.envs.highway.lane_keeping_fields import LaneKeepingFields, lane_index_of
from torchrl_grpo.envs.highway.layout import KIND, EntityLayout
from torchrl_grpo.envs.highway.layout import NONE as _NONE

# check_magnitude (env_checks), lane_index_of (lane_keeping_fields) and time_limit
# (core.gym_state) moved out; re-exported from here, where they were defined.
__all__ = ["EnvFields", "check_magnitude", "lane_index_of", "time_limit"]

# Name-mangled private attributes of highway-env's action / observation types.
_ACTION_VEHICLE = "_ActionType__controlled_vehicle"
_OBSERVER = "_ObservationType__observer_vehicle"

# Attributes of the unwrapped env that are fixed by the config or render-only.
_ENV_STATIC = frozenset(
    {
        "_np_random",
        "_np_random_seed",
        "_record_video_wrapper",
        "action_space",
        "action_type",
        "config",
        "controlled_vehicles",
        "done",
        "enable_auto_render",
        "observation_space",
        "observation_type",
        "observation_type_parking",
        "render_mode",
        "road",
        "spec",
        "steps",
        "time",
        "viewer",
        "interval_trajectory",
        "lpv",
        "lane",
        "lanes",
        "trajectory",
    }
)


class EnvFields:
    """Encodes and restores the env-level attributes of one bound highway-env env.

    Args:
        env: the freshly reset env the codec binds to.
        layout: the codec's entity layout (for lane codes).
        class_parameters: the process-global class constants a state carries.
        max_trajectory: rows kept of lane-keeping's ``trajectory`` (``None``: the
            TimeLimit plus 8).

    Example:
        >>> import gymnasium as gym
        >>> from torchrl_grpo.envs.highway.highway_codec import HighwayStateCodec
        >>> env = gym.make("highway-fast-v0")
        >>> _ = env.reset(seed=0)
        >>> codec = HighwayStateCodec()
        >>> codec.bind(env)
        >>> sorted(codec.env_fields.spec())[:4]
        ['action_vehicle', 'class_params', 'controlled', 'done']
    """

    def __init__(
        self,
        env: gym.Env,
        layout: EntityLayout,
        class_parameters: list[tuple[type, str]],
        max_trajectory: int | None = None,
    ) -> None:
        core = env.unwrapped
        obs_type = core.observation_type
        self.layout = layout
        self.class_parameters = class_parameters
        self.n_controlled = len(core.controlled_vehicles)
        self.lane_keeping = LaneKeepingFields(env, layout, max_trajectory)
        self.max_trajectory = self.lane_keeping.max_trajectory
        self.continuous_action = isinstance(core.action_type, ContinuousAction)
        self.action_size = core.action_type.size if self.continuous_action else 0
        self.kinematic_obs = isinstance(obs_type, KinematicObservation)
        # Goal observations read the observer's goal (parking-v0 rewards through one).
        self.goal_observed = isinstance(obs_type, KinematicsGoalObservation)
        self.goal_rewarded = isinstance(
            getattr(core, "observation_type_parking", None), KinematicsGoalObservation
        )
        self.range_keys = list(obs_type.features) if self.kinematic_obs else []
        if self.kinematic_obs and obs_type.features_range:
            self.range_keys += [k for k in obs_type.features_range if k not in self.range_keys]
        self.grayscale_shape = (
            obs_type.shape if isinstance(obs_type, GrayscaleObservation) else None
        )

    def spec(self) -> dict[str, Unbounded]:
        """The env-level entries' specs (floats in their own dtype; the codec stores bits)."""

        def u(shape: tuple[int, ...], dtype: torch.dtype) -> Unbounded:
            return Unbounded(shape, dtype=dtype)

        env = {
            "time": u((), torch.float64),
            "steps": u((), torch.int64),
            "done": u((), torch.bool),
            "seed": u((), torch.int64),
            "rng": u((RNG_WORDS,), torch.int64),
            "road_steps": u((), torch.int64),
            "class_params": u((len(self.class_parameters),), torch.float64),
            "controlled": u((self.n_controlled,), torch.int64),
            "action_vehicle": u((), torch.int64),
            "observer_vehicle": u((), torch.int64),
            "last_action": u((self.action_size,), torch.float64),
            "features_range": u((len(self.range_keys), 2), torch.float64),
            "features_range_mask": u((len(self.range_keys),), torch.bool),
            **self.lane_keeping.spec(),
        }
        if self.grayscale_shape is not None:
            env["frames"] = u(tuple(self.grayscale_shape), torch.uint8)
        return env

    def encode(self, env: gym.Env, slot: dict[int, int]) -> dict:
        """The env-level arrays of ``env``'s state (``slot``: entity slot by object id)."""
        core = env.unwrapped
        unknown = vars(core).keys() - _ENV_STATIC
        if unknown:
            raise UnknownFieldError(
                f"{type(core).__qualname__} has env-level attributes the highway codec does "
                f"not store: {sorted(unknown)}; subclass HighwayStateCodec to add them"
            )
        out: dict[tuple[str, str], np.ndarray] = {}

        def put(key: str, value: Any, dtype: Any) -> None:
            out[("env", key)] = np.asarray(value, dtype=dtype)

        put("time", core.time, np.float64)
        put("steps", core.steps, np.int64)
        put("done", core.done, np.bool_)
        seed = core._np_random_seed
        put("seed", _NONE if seed is None or seed >= 2**63 else seed, np.int64)
        rng = np.zeros(RNG_WORDS, dtype=np.int64)
        encode_rng(core.np_random, rng)
        out[("env", "rng")] = rng
        put("road_steps", getattr(core.road, "steps", _NONE), np.int64)
        put("class_params", [getattr(c, n) for c, n in self.class_parameters], np.float64)
        if len(core.controlled_vehicles) != self.n_controlled:
            raise StateCapacityError(
                f"{len(core.controlled_vehicles)} controlled vehicles, the layout holds "
                f"{self.n_controlled}"
            )
        put("controlled", [slot[id(v)] for v in core.controlled_vehicles], np.int64)
        action_vehicle = getattr(core.action_type, _ACTION_VEHICLE, None)
        observer = getattr(core.observation_type, _OBSERVER, None)
        put(
            "action_vehicle",
            _NONE if action_vehicle is None else slot[id(action_vehicle)],
            np.int64,
        )
        put("observer_vehicle", _NONE if observer is None else slot[id(observer)], np.int64)
        put(
            "last_action",
            core.action_type.last_action if self.continuous_action else [],
            np.float64,
        )
        ranges = np.zeros((len(self.range_keys), 2))
        mask = np.zeros(len(self.range_keys), dtype=np.bool_)
        features_range = core.observation_type.features_range if self.kinematic_obs else None
        for key, bounds in (features_range or {}).items():
            if key not in self.range_keys:
                raise UnknownFieldError(f"observation features_range has an unknown key {key!r}")
            ranges[self.range_keys.index(key)] = bounds
            mask[self.range_keys.index(key)] = True
        out[("env", "features_range")] = ranges
        out[("env", "features_range_mask")] = mask
        out.update(self.lane_keeping.encode(env))
        if self.grayscale_shape is not None:
            out[("env", "frames")] = np.array(core.observation_type.obs, dtype=np.uint8)
        return out

    def decode(self, core: Any, t: dict[Any, torch.Tensor], by_slot: dict) -> dict:
        """Check the env-level entries ``t`` and build what a restore writes (nothing written)."""
        # Scalars through .item() and vectors through .tolist(): both give the exact
        # Python values, for a fraction of the cost of a numpy view per entry.
        kinds = t[("entities", "i16")][:, KIND].tolist()

        def vehicle_at(code: int, what: str) -> Any:
            return vehicle_in_slot(code, f"env.{what}", by_slot, kinds)

        def floats(key: str) -> torch.Tensor:
            return t[("env", key)].view(torch.float64)

        seed = t[("env", "seed")].item()
        road_steps = t[("env", "road_steps")].item()
        for key in ("time", "class_params", "last_action", "features_range"):
            check_magnitude(f"env.{key}", floats(key))
        plan: dict[str, Any] = {
            "time": floats("time").item(),
            "steps": t[("env", "steps")].item(),
            "done": t[("env", "done")].item(),
            "seed": None if seed < 0 else seed,
            "rng": decode_rng(t[("env", "rng")].numpy(), "env.rng"),
            "road_steps": None if road_steps < 0 else road_steps,
        }
        if plan["steps"] < 0:
            raise StateCorruptedError(f"env.steps is {plan['steps']}, not a count")
        if (plan["road_steps"] is None) == hasattr(core.road, "steps"):
            raise StateCorruptedError(
                f"env.road_steps is {road_steps}, but this road "
                + ("counts steps" if hasattr(core.road, "steps") else "has no step counter")
            )
        plan |= {
            "class_params": floats("class_params").tolist(),
            "controlled": [vehicle_at(c, "controlled") for c in t[("env", "controlled")].tolist()],
            "action_vehicle": vehicle_at(t[("env", "action_vehicle")].item(), "action_vehicle"),
            "observer_vehicle": vehicle_at(
                t[("env", "observer_vehicle")].item(), "observer_vehicle"
            ),
            "last_action": floats("last_action").numpy().copy(),
        }
        if None in plan["controlled"]:
            raise StateCorruptedError("env.controlled holds an empty slot")
        self.check_goals(plan, by_slot)
        check_class_parameters(self.class_parameters, plan["class_params"])
        ranges = zip(
            self.range_keys,
            floats("features_range").tolist(),
            t[("env", "features_range_mask")].tolist(),
            strict=True,
        )
        plan["features_range"] = {k: r for k, r, m in ranges if m} or None
        check_features_range(plan["features_range"])
        plan |= self.lane_keeping.decode(core, t)
        if self.grayscale_shape is not None:
            plan["frames"] = t[("env", "frames")].numpy().copy()
        return plan

    def check_goals(self, plan: dict[str, Any], by_slot: dict[int, Any]) -> None:
        """Refuse a plan whose goal observations observe a vehicle without a goal.

        The observation's observer defaults to the first controlled vehicle, as
        highway-env's does; parking-v0 also observes that vehicle's goal for its reward.
        """
        if not (self.goal_observed or self.goal_rewarded):
            return
        first = plan["controlled"][0] if plan["controlled"] else None
        slot_of = {id(obj): slot for slot, obj in by_slot.items()}
        if self.goal_observed:
            observer = plan["observer_vehicle"] or first
            check_observed_goal(observer, "the observation (env.observer_vehicle)", slot_of)
        if self.goal_rewarded:
            check_observed_goal(first, "the reward (env.controlled)", slot_of)

    def commit(self, env: gym.Env, plan: dict[str, Any]) -> None:
        """Write a decoded plan's env-level part into ``env`` (cannot fail)."""
        core = env.unwrapped
        road = core.road
        for (cls, name), value in zip(self.class_parameters, plan["class_params"], strict=True):
            setattr(cls, name, value)
        core.np_random.bit_generator.state = plan["rng"]
        core.time, core.steps, core.done = plan["time"], plan["steps"], plan["done"]
        core._np_random_seed = plan["seed"]
        if plan["road_steps"] is not None:
            road.steps = plan["road_steps"]
        core.controlled_vehicles = plan["controlled"]
        if hasattr(core.action_type, _ACTION_VEHICLE):
            setattr(core.action_type, _ACTION_VEHICLE, plan["action_vehicle"])
        if hasattr(core.observation_type, _OBSERVER):
            setattr(core.observation_type, _OBSERVER, plan["observer_vehicle"])
        if self.continuous_action:
            core.action_type.last_action = plan["last_action"]
        if self.kinematic_obs:
            core.observation_type.features_range = plan["features_range"]
        self.lane_keeping.commit(core, plan)
        if self.grayscale_shape is not None:
            core.observation_type.obs = plan["frames"]
        restore_wrappers(env, *plan["wrappers"])
