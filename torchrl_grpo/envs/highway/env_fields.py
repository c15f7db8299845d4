"""The env-level part of a highway-env state: everything that is not a road object.

Time and counters, the generator, which vehicles are controlled, acted on and
observed, the action and observation types' own state (a continuous action's last
command, the Kinematics ``features_range``, grayscale frames), and the extras of
lane-keeping and racetrack (env-level lanes and the growing trajectory). Built by
:class:`~torchrl_grpo.envs.HighwayStateCodec` when it binds to an env.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from highway_env.envs.common.action import ContinuousAction
from highway_env.envs.common.observation import GrayscaleObservation, KinematicObservation
from torchrl.data import Unbounded

from torchrl_grpo.envs.core.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    UnknownFieldError,
)
from torchrl_grpo.envs.core.gym_state import RNG_WORDS, decode_rng, encode_rng, restore_wrappers
from torchrl_grpo.envs.highway.layout import NONE as _NONE
from torchrl_grpo.envs.highway.layout import EntityLayout
from torchrl_grpo.envs.highway.schema import CLASS_PARAMETER_DOMAINS, MAX_MAGNITUDE

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
        >>> from torchrl_grpo.envs import HighwayStateCodec
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
        self.has_lane = hasattr(core, "lane")
        self.has_lanes = hasattr(core, "lanes")
        self.has_trajectory = hasattr(core, "trajectory")
        limit = time_limit(env)
        self.max_trajectory = max_trajectory or (limit + 8 if limit else 1024)
        self.continuous_action = isinstance(core.action_type, ContinuousAction)
        self.action_size = core.action_type.size if self.continuous_action else 0
        self.kinematic_obs = isinstance(obs_type, KinematicObservation)
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
            "lane": u((3,), torch.int64),
            "lanes": u((4, 3), torch.int64),
            "lanes_len": u((), torch.int64),
            "trajectory": u((self.max_trajectory if self.has_trajectory else 0, 6), torch.float64),
            "trajectory_len": u((), torch.int64),
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
        lane = np.full(3, _NONE - 1, dtype=np.int64)  # -2: no env-level lane
        if self.has_lane and core.lane is not None:
            lane[:] = self.layout.lane_code(lane_index_of(core.road.network, core.lane))
        out[("env", "lane")] = lane
        lanes = np.zeros((4, 3), dtype=np.int64)
        lane_list = core.lanes if self.has_lanes else []
        for j, each in enumerate(lane_list):
            lanes[j] = self.layout.lane_code(lane_index_of(core.road.network, each))
        out[("env", "lanes")] = lanes
        put("lanes_len", len(lane_list), np.int64)
        rows = self.max_trajectory if self.has_trajectory else 0
        trajectory = np.zeros((rows, 6))
        points = core.trajectory if self.has_trajectory else []
        if len(points) > rows:
            raise StateCapacityError(
                f"the trajectory holds {len(points)} points, the state pads to {rows}: "
                "build the env with a larger max_trajectory"
            )
        if points:
            trajectory[: len(points)] = np.asarray(points).reshape(len(points), 6)
        out[("env", "trajectory")] = trajectory
        put("trajectory_len", len(points), np.int64)
        if getattr(core, "interval_trajectory", None):
            raise SnapshotError("lane-keeping interval trajectories are not supported")
        if self.grayscale_shape is not None:
            out[("env", "frames")] = np.array(core.observation_type.obs, dtype=np.uint8)
        return out

    def decode(self, core: Any, t: dict[Any, torch.Tensor], by_slot: dict) -> dict:
        """Check the env-level entries ``t`` and build what a restore writes (nothing written)."""

        # Scalars through .item() and vectors through .tolist(): both give the exact
        # Python values, for a fraction of the cost of a numpy view per entry.
        def vehicle_at(code: int, what: str) -> Any:
            if code == _NONE:
                return None
            if code not in by_slot:
                raise StateCorruptedError(f"env.{what} refers to empty slot {code}")
            return by_slot[code]

        def floats(key: str) -> torch.Tensor:
            return t[("env", key)].view(torch.float64)

        seed = t[("env", "seed")].item()
        road_steps = t[("env", "road_steps")].item()
        n_points = t[("env", "trajectory_len")].item()
        trajectory = t[("env", "trajectory")]
        if not 0 <= n_points <= trajectory.shape[0]:
            raise StateCorruptedError(f"env.trajectory_len is {n_points}")
        for key in ("time", "class_params", "last_action", "features_range"):
            check_magnitude(f"env.{key}", floats(key))
        check_magnitude("env.trajectory", trajectory[:n_points].view(torch.float64))
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
        for (cls, name), value in zip(self.class_parameters, plan["class_params"], strict=True):
            low, high = CLASS_PARAMETER_DOMAINS.get((cls, name), (-math.inf, math.inf))
            if not low < value < high:
                raise StateCorruptedError(
                    f"env.class_params: {cls.__qualname__}.{name} is {value}, "
                    f"outside ({low}, {high})"
                )
        ranges = zip(
            self.range_keys,
            floats("features_range").tolist(),
            t[("env", "features_range_mask")].tolist(),
            strict=True,
        )
        plan["features_range"] = {k: r for k, r, m in ranges if m} or None
        for key, (low, high) in (plan["features_range"] or {}).items():
            if not low < high:
                raise StateCorruptedError(
                    f"env.features_range: {key} (set in env.features_range_mask) spans "
                    f"[{low}, {high}]"
                )
        lane_code = t[("env", "lane")].tolist()
        plan["lane"] = (
            None if lane_code[0] == _NONE - 1 else self.lane_object(core, lane_code, "env.lane")
        )
        n_lanes = t[("env", "lanes_len")].item()
        if not 0 <= n_lanes <= 4:
            raise StateCorruptedError(f"env.lanes_len is {n_lanes}")
        where = f"env.lanes (of env.lanes_len {n_lanes})"
        plan["lanes"] = [
            self.lane_object(core, c, where) for c in t[("env", "lanes")].tolist()[:n_lanes]
        ]
        points = trajectory[:n_points].view(torch.float64).numpy()
        plan["trajectory"] = [p.reshape(6, 1).copy() for p in points]
        if self.grayscale_shape is not None:
            plan["frames"] = t[("env", "frames")].numpy().copy()
        return plan

    def lane_object(self, core: Any, code: list[int], where: str) -> Any:
        """The lane object of a stored lane code (``where`` names the entry in errors)."""
        index = self.layout.lane_index(code, where)
        try:
            return core.road.network.get_lane(index)
        except (KeyError, IndexError) as err:
            raise StateCorruptedError(f"{where}: lane {index} is not on this road") from err

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
        if self.has_lane:
            core.lane = plan["lane"]
        if self.has_lanes:
            core.lanes = plan["lanes"]
        if self.has_trajectory:
            core.trajectory = plan["trajectory"]
        if self.grayscale_shape is not None:
            core.observation_type.obs = plan["frames"]
        restore_wrappers(env, *plan["wrappers"])


def check_magnitude(where: str, values: torch.Tensor) -> None:
    """Refuse NaN, inf and magnitudes beyond :data:`~.schema.MAX_MAGNITUDE` in ``values``.

    Example:
        >>> check_magnitude("env.time", torch.tensor([1.5], dtype=torch.float64))
        >>> try:
        ...     check_magnitude("env.time", torch.tensor([float("nan")], dtype=torch.float64))
        ... except StateCorruptedError as err:
        ...     print(err)
        env.time holds nan: not finite, or beyond 1e+09
    """
    bad = ~(values.abs() <= MAX_MAGNITUDE)  # NaN fails the comparison
    if bool(bad.any()):
        raise StateCorruptedError(
            f"{where} holds {values[bad][0].item()}: not finite, or beyond {MAX_MAGNITUDE:g}"
        )


def lane_index_of(network: Any, lane: Any) -> tuple:
    """The ``(from, to, id)`` index of a lane object of ``network``.

    Example:
        >>> from highway_env.road.road import RoadNetwork
        >>> net = RoadNetwork.straight_road_network(2)
        >>> lane_index_of(net, net.get_lane(("0", "1", 1)))
        ('0', '1', 1)
    """
    for start, destinations in network.graph.items():
        for end, lanes in destinations.items():
            for lane_id, candidate in enumerate(lanes):
                if candidate is lane:
                    return (start, end, lane_id)
    raise SnapshotError("an env-level lane is not part of the road network")


def time_limit(env: gym.Env) -> int | None:
    """The ``TimeLimit`` wrapper's limit of ``env``, or ``None``.

    Example:
        >>> time_limit(gym.make("CartPole-v1"))
        500
    """
    while isinstance(env, gym.Wrapper):
        if isinstance(env, gym.wrappers.TimeLimit):
            return env._max_episode_steps
        env = env.env
    return None
