"""The complete state of a highway-env scenario as a fixed-shape TensorDict.

Layout of a state::

    fingerprint/   config, road, layout          int64: what the state belongs to
    env/           time, steps, done, seed, rng, road_steps, class_params,
                   controlled (entity slots of env.controlled_vehicles),
                   action_vehicle, observer_vehicle, last_action, features_range...,
                   lane, lanes, trajectory (lane-keeping / racetrack extras)
    wrappers/      elapsed_steps (TimeLimit), has_reset (OrderEnforcing)
    entities/      f64, i16, i64, flags: one row per road object, packed by
                   :class:`~torchrl_grpo.envs.highway.layout.EntityLayout`
                   (``codec.layout.column(entities, "speed")`` reads a field back)

Slots ``[0, max_vehicles)`` hold ``road.vehicles`` and the rest ``road.objects``;
road objects keep their list order (acting and collision checks iterate in that
order). The road network is not stored: it is fixed by the config, so it is
fingerprinted instead and the restoring env's own network is reused.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from highway_env.envs.common.action import ContinuousAction
from highway_env.envs.common.observation import (
    GrayscaleObservation,
    KinematicObservation,
    MultiAgentObservation,
    TupleObservation,
)
from highway_env.vehicle.dynamics import BicycleVehicle
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.core.bits import (
    bits_spec,
    check_state_layout,
    nested_tensordict,
    spec_layout,
)
from torchrl_grpo.envs.core.codec import StateCodec, stable_hash
from torchrl_grpo.envs.core.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    StateMismatchError,
    UnknownFieldError,
)
from torchrl_grpo.envs.core.gym_state import (
    RNG_WORDS,
    decode_rng,
    encode_rng,
    encode_wrappers,
    restore_wrappers,
    with_seeded_rng,
    wrapper_spec,
)
from torchrl_grpo.envs.core.registry import register_codec
from torchrl_grpo.envs.highway import schema
from torchrl_grpo.envs.highway.layout import KIND, OBJECT, VEHICLE, EntityLayout
from torchrl_grpo.envs.highway.layout import NONE as _NONE

# Fields every road object has (RoadObject.__init__ sets them); a restored object
# without them would fail later, in the middle of a step.
_REQUIRED_FIELDS = frozenset(
    {
        "position",
        "heading",
        "speed",
        "lane_index",
        "collidable",
        "solid",
        "check_collisions",
        "diagonal",
        "crashed",
        "hit",
    }
)
_NOT_NONE = ("position", "heading", "speed")

#: Every scenario highway-env 1.12 ships: HighwayEnv and the codec serve them all.
HIGHWAY_SCENARIOS: tuple[str, ...] = (
    "highway-v0",
    "highway-fast-v0",
    "merge-v0",
    "roundabout-v0",
    "intersection-v0",
    "racetrack-v0",
    "parking-v0",
    "exit-v0",
    "u-turn-v0",
    "two-way-v0",
    "lane-keeping-v0",
)
_SPAWN_CAPACITY = 32  # vehicle slots of scenarios that spawn traffic (intersection-v0)
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


class HighwayStateCodec(StateCodec):
    """Snapshots every highway-env scenario into tensors, exactly.

    Args:
        max_vehicles: slots for ``road.vehicles``; defaults to the count after the
            first reset, or 32 in scenarios that spawn traffic (intersection-v0).
        max_objects: slots for ``road.objects``; defaults to the count after reset.
        max_trajectory: rows kept of lane-keeping's growing ``trajectory``; defaults
            to the TimeLimit plus 8.

    Example:
        >>> import gymnasium as gym
        >>> import highway_env  # noqa: F401 - registers the scenarios
        >>> env = gym.make("merge-v0")
        >>> _ = env.reset(seed=0)
        >>> codec = HighwayStateCodec()
        >>> codec.bind(env)
        >>> state = codec.encode(env)
        >>> for _ in range(3):
        ...     _ = env.step(1)
        >>> codec.decode(env, state)
        >>> from torchrl_grpo.envs import states_equal
        >>> states_equal(codec.encode(env), state)
        True
    """

    def __init__(
        self,
        max_vehicles: int | None = None,
        max_objects: int | None = None,
        max_trajectory: int | None = None,
    ) -> None:
        self._max_vehicles = max_vehicles
        self._max_objects = max_objects
        self._max_trajectory = max_trajectory
        self._bound = False

    # ------------------------------------------------------------------ binding
    def bind(self, env: gym.Env) -> None:
        """Fix the layout from a freshly reset env: capacities, vocabulary, node names."""
        core = env.unwrapped
        road = core.road
        if road is None:
            raise SnapshotError("bind() needs an env that has been reset")
        obs_type = core.observation_type
        if isinstance(obs_type, (MultiAgentObservation, TupleObservation)):
            raise SnapshotError(
                f"{type(obs_type).__name__} is not supported: use a single-agent observation"
            )
        if getattr(core, "lpv", None) is not None:
            raise SnapshotError("lane-keeping with an LPV interval predictor is not supported")
        self.classes = list(schema.VEHICLE_CLASSES)
        self.class_index = {cls: i for i, cls in enumerate(self.classes)}
        self.class_parameters = list(schema.CLASS_PARAMETERS)
        spawns = "spawn_probability" in core.config
        # Spawning scenarios get a fixed default, so that envs built with different seeds
        # (ParallelEnv workers) share one layout and can exchange states.
        default = max(_SPAWN_CAPACITY, len(road.vehicles) + 16) if spawns else len(road.vehicles)
        self.max_vehicles = self._max_vehicles or default
        self.max_objects = self._max_objects or len(road.objects)
        self.n_controlled = len(core.controlled_vehicles)
        nodes = sorted(_road_nodes(road.network), key=repr)
        speeds = [len(v.target_speeds) for v in road.vehicles if hasattr(v, "target_speeds")]
        self.layout = EntityLayout(
            schema.FIELDS,
            capacity=self.max_vehicles + self.max_objects,
            nodes=nodes,
            # A planned route is a shortest path: it visits each node at most once.
            max_route=min(16, len(nodes)),
            max_speeds=max(speeds, default=0),
            required=_REQUIRED_FIELDS,
            not_none=_NOT_NONE,
        )
        position = self.layout.columns["position"]
        self._position_columns = slice(position.start, position.stop)
        self._history_sizes: dict[type, int | None] = {}
        self.has_lane = hasattr(core, "lane")
        self.has_lanes = hasattr(core, "lanes")
        self.has_trajectory = hasattr(core, "trajectory")
        limit = _time_limit(env)
        self.max_trajectory = self._max_trajectory or (limit + 8 if limit else 1024)
        self.continuous_action = isinstance(core.action_type, ContinuousAction)
        self.action_size = core.action_type.size if self.continuous_action else 0
        self.kinematic_obs = isinstance(obs_type, KinematicObservation)
        self.range_keys = list(obs_type.features) if self.kinematic_obs else []
        if self.kinematic_obs and obs_type.features_range:
            self.range_keys += [k for k in obs_type.features_range if k not in self.range_keys]
        self.grayscale_shape = (
            obs_type.shape if isinstance(obs_type, GrayscaleObservation) else None
        )
        self.fingerprints = {
            "config": stable_hash(core.spec.id if core.spec else type(core).__name__, core.config),
            "road": stable_hash(_describe(road.network)),
            "layout": stable_hash(
                [(n, f.kind, f.shape, f.choices) for n, f in self.layout.fields.items()],
                [f"{c.__module__}.{c.__qualname__}" for c in self.classes],
                [f"{c.__qualname__}.{n}" for c, n in self.class_parameters],
                self.layout.widths,
                self.max_vehicles,
                self.max_objects,
                self.max_trajectory,
                self.n_controlled,
            ),
        }
        self._spec, float_keys = bits_spec(self._build_spec())
        self._float_keys = {_dotted(k) for k in float_keys}
        self._spec_layout = spec_layout(self._spec)
        self._bound = True

    def fingerprint(self, env: gym.Env) -> int:
        """A hash of the config, the road network and the state layout."""
        return stable_hash(self.fingerprints)

    def state_spec(self) -> Composite:
        """See :meth:`StateCodec.state_spec`."""
        return self._spec.clone()

    def _build_spec(self) -> Composite:
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
        entities = {k: u(shape, dtype) for k, (shape, dtype) in self.layout.spec_shapes().items()}
        return Composite(
            fingerprint=Composite(
                config=u((), torch.int64), road=u((), torch.int64), layout=u((), torch.int64)
            ),
            env=Composite(env),
            wrappers=wrapper_spec(),
            entities=Composite(entities),
        )

    # ------------------------------------------------------------------ encode
    def encode(self, env: gym.Env) -> TensorDictBase:
        """See :meth:`StateCodec.encode`."""
        self._check_bound()
        road = env.unwrapped.road
        if len(road.vehicles) > self.max_vehicles or len(road.objects) > self.max_objects:
            raise StateCapacityError(
                f"the road holds {len(road.vehicles)} vehicles and {len(road.objects)} objects; "
                f"this env's state pads to {self.max_vehicles} and {self.max_objects}. "
                "Build the env with a larger max_vehicles / max_objects."
            )
        items = [(i, VEHICLE, v) for i, v in enumerate(road.vehicles)]
        items += [(self.max_vehicles + i, OBJECT, o) for i, o in enumerate(road.objects)]
        slot = {id(obj): i for i, _, obj in items}
        arrays = {
            ("entities", k): v for k, v in self.layout.encode(items, self.class_index).items()
        }
        arrays.update(self._encode_env(env, slot))
        for key, value in self.fingerprints.items():
            arrays[("fingerprint", key)] = np.asarray(value, dtype=np.int64)
        for key, value in encode_wrappers(env).items():
            arrays[("wrappers", key)] = value
        # Floats are stored as their int64 bit patterns (see codec.FLOAT_BITS).
        return nested_tensordict(
            {
                k: torch.from_numpy(v.view(np.int64) if v.dtype == np.float64 else v)
                for k, v in arrays.items()
            }
        )

    def _encode_env(self, env: gym.Env, slot: dict[int, int]) -> dict:
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
            lane[:] = self.layout.lane_code(_lane_index_of(core.road.network, core.lane))
        out[("env", "lane")] = lane
        lanes = np.zeros((4, 3), dtype=np.int64)
        lane_list = core.lanes if self.has_lanes else []
        for j, each in enumerate(lane_list):
            lanes[j] = self.layout.lane_code(_lane_index_of(core.road.network, each))
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

    def reseed(self, state: TensorDictBase, seed: int) -> TensorDictBase:
        """See :meth:`StateCodec.reseed`: replaces the ``("env", "rng")`` words.

        ``("env", "seed")`` (gymnasium's record of the episode's reset seed) is kept.
        The new stream shows wherever the simulator draws after the state was taken:
        intersection-v0 spawns traffic from it at every step, most other scenarios
        draw at reset only (so a reseeded state changes their next episode).
        """
        return with_seeded_rng(state, ("env", "rng"), seed)

    # ------------------------------------------------------------------ decode
    def check_compatible(self, state: TensorDictBase) -> None:
        """Raise :class:`StateMismatchError` unless ``state`` carries this env's fingerprints."""
        self._check_bound()
        if not isinstance(state, TensorDictBase) or "fingerprint" not in state.keys():
            raise StateMismatchError(
                "the state has no highway-env fingerprint: it was not captured by a HighwayEnv"
            )
        for key, expected in self.fingerprints.items():
            found = state.get(("fingerprint", key), None)
            if found is None:
                raise StateCorruptedError(
                    f"the state is truncated: missing entry fingerprint.{key}"
                )
            if not isinstance(found, torch.Tensor) or found.numel() != 1:
                raise StateCorruptedError(f"the state's fingerprint.{key} is malformed")
            if int(found) != expected:
                what = {
                    "config": "another scenario or config",
                    "road": "another road network",
                    "layout": "an env with another state layout (padding or registered classes)",
                }[key]
                raise StateMismatchError(
                    f"the state was captured from {what}: fingerprint.{key} is {int(found)}, "
                    f"this env's is {expected}"
                )

    def decode(self, env: gym.Env, state: TensorDictBase) -> None:
        """See :meth:`StateCodec.decode`."""
        self._commit(env, self._prepare(env, state))

    def validate(self, env: gym.Env, state: TensorDictBase) -> None:
        """See :meth:`StateCodec.validate`: the checks of :meth:`decode`, nothing written."""
        self._prepare(env, state)

    def _prepare(self, env: gym.Env, state: TensorDictBase) -> dict[str, Any]:
        """Validate ``state`` and build everything a restore writes, without writing it."""
        self.check_compatible(state)
        found = check_state_layout(state, self._spec_layout)
        core = env.unwrapped
        # Entities as numpy views (no copy); f64 holds float64 bit patterns.
        blocks = {b: found[("entities", b)].numpy() for b in self.layout.widths}
        blocks["f64"] = blocks["f64"].view(np.float64)
        vehicles, objects, by_slot = self._decode_entities(core, blocks)
        plan = self._decode_env(core, found, by_slot)
        plan["vehicles"], plan["objects"] = vehicles, objects
        plan["wrappers"] = (
            found[("wrappers", "elapsed_steps")].item(),
            found[("wrappers", "has_reset")].item(),
        )
        return plan

    def _commit(self, env: gym.Env, plan: dict[str, Any]) -> None:
        # Everything is built and validated: from here on nothing can fail.
        core = env.unwrapped
        road = core.road
        road.vehicles[:] = plan["vehicles"]
        road.objects[:] = plan["objects"]
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

    def _decode_entities(self, core: Any, blocks: dict[str, np.ndarray]) -> tuple[list, list, dict]:
        # Checks every slot (kind, class, required fields, values) before building lists.
        decoded = self.layout.decode(blocks, self.classes)
        by_slot = {slot: obj for slot, _, obj, _ in decoded}
        slots = np.fromiter((slot for slot, _, _, _ in decoded), dtype=np.int64, count=len(decoded))
        kinds = blocks["i16"][slots, KIND]
        wrong = np.flatnonzero((kinds == VEHICLE) != (slots < self.max_vehicles))
        if wrong.size:
            slot = int(slots[wrong[0]])
            raise StateCorruptedError(
                f"entities: slot {slot} holds the wrong kind {int(kinds[wrong[0]])}"
            )
        # Every slot has a position by now (a required, non-None field): check them at once.
        positions = blocks["f64"][slots, self._position_columns]
        finite = np.isfinite(positions).all(axis=1)
        if not finite.all():
            bad = int(np.flatnonzero(~finite)[0])
            raise StateCorruptedError(
                f"entity slot {int(slots[bad])}: non-finite position {positions[bad]}"
            )
        vehicles, objects = [], []
        for slot, kind, obj, refs in decoded:
            for name, target in refs.items():
                if target not in by_slot:
                    raise StateCorruptedError(
                        f"entities.{name} of slot {slot} is empty slot {target}"
                    )
                obj.__dict__[name] = by_slot[target]
            try:
                self._rebuild_derived(core, obj, slot)
            except (AttributeError, TypeError, ValueError) as err:
                raise StateCorruptedError(f"entity slot {slot} cannot be rebuilt: {err}") from err
            (vehicles if kind == VEHICLE else objects).append(obj)
        return vehicles, objects, by_slot

    def _rebuild_derived(self, core: Any, obj: Any, slot: int) -> None:
        d = obj.__dict__
        d["road"] = core.road
        lane_index = d["lane_index"]  # required: checked by the layout
        try:
            d["lane"] = None if lane_index is None else core.road.network.get_lane(lane_index)
        except (KeyError, IndexError) as err:
            raise StateCorruptedError(
                f"entity slot {slot}: lane {lane_index} is not on this road"
            ) from err
        cls = type(obj)
        if cls not in self._history_sizes:
            self._history_sizes[cls] = getattr(cls, "HISTORY_SIZE", None)
        history = self._history_sizes[cls]
        if history is not None:
            d["log"] = []
            d["history"] = deque(maxlen=history)
        if isinstance(obj, BicycleVehicle):
            d["A_lat"], d["B_lat"] = obj.lateral_lpv_dynamics()  # also sets theta

    def _decode_env(self, core: Any, t: dict[Any, torch.Tensor], by_slot: dict) -> dict:
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
        plan: dict[str, Any] = {
            "time": floats("time").item(),
            "steps": t[("env", "steps")].item(),
            "done": t[("env", "done")].item(),
            "seed": None if seed < 0 else seed,
            "rng": decode_rng(t[("env", "rng")].numpy()),
            "road_steps": None if road_steps < 0 else road_steps,
        }
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
        if not math.isfinite(plan["time"]):
            raise StateCorruptedError(f"env.time is {plan['time']}")
        ranges = zip(
            self.range_keys,
            floats("features_range").tolist(),
            t[("env", "features_range_mask")].tolist(),
            strict=True,
        )
        plan["features_range"] = {k: r for k, r, m in ranges if m} or None
        lane_code = t[("env", "lane")].tolist()
        plan["lane"] = (
            None if lane_code[0] == _NONE - 1 else self._lane_object(core, lane_code, "env.lane")
        )
        n_lanes = t[("env", "lanes_len")].item()
        if not 0 <= n_lanes <= 4:
            raise StateCorruptedError(f"env.lanes_len is {n_lanes}")
        plan["lanes"] = [
            self._lane_object(core, c, "env.lanes") for c in t[("env", "lanes")].tolist()[:n_lanes]
        ]
        n_points = t[("env", "trajectory_len")].item()
        trajectory = t[("env", "trajectory")]
        if not 0 <= n_points <= trajectory.shape[0]:
            raise StateCorruptedError(f"env.trajectory_len is {n_points}")
        points = trajectory[:n_points].view(torch.float64).numpy()
        plan["trajectory"] = [p.reshape(6, 1).copy() for p in points]
        if self.grayscale_shape is not None:
            plan["frames"] = t[("env", "frames")].numpy().copy()
        return plan

    def _lane_object(self, core: Any, code: list[int], where: str) -> Any:
        index = self.layout.lane_index(code, where)
        try:
            return core.road.network.get_lane(index)
        except (KeyError, IndexError) as err:
            raise StateCorruptedError(f"{where}: lane {index} is not on this road") from err

    def _check_bound(self) -> None:
        if not self._bound:
            raise SnapshotError("the codec is not bound to an env: call bind(env) first")


def _dotted(key: str | tuple[str, ...]) -> str:
    return ".".join(key) if isinstance(key, tuple) else key


def _road_nodes(network: Any) -> set:
    nodes = set(network.graph)
    for destinations in network.graph.values():
        nodes.update(destinations)
    return nodes


def _lane_index_of(network: Any, lane: Any) -> tuple:
    for start, destinations in network.graph.items():
        for end, lanes in destinations.items():
            for lane_id, candidate in enumerate(lanes):
                if candidate is lane:
                    return (start, end, lane_id)
    raise SnapshotError("an env-level lane is not part of the road network")


def _time_limit(env: gym.Env) -> int | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, gym.wrappers.TimeLimit):
            return env._max_episode_steps
        env = env.env
    return None


def _describe(obj: Any, depth: int = 0) -> Any:
    """A process-independent, JSON-able description of a road network (no addresses)."""
    if depth > 6:
        return type(obj).__name__
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, dict):
        return {repr(k): _describe(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_describe(v, depth + 1) for v in obj]
    if hasattr(obj, "__dict__"):
        return [type(obj).__name__, _describe(vars(obj), depth + 1)]
    return type(obj).__name__


for _scenario in HIGHWAY_SCENARIOS:
    register_codec(_scenario, HighwayStateCodec)
