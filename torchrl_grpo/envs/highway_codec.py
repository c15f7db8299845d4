"""The complete state of a highway-env scenario as a fixed-shape TensorDict.

Layout of a state (``M`` entity slots, ``F`` vocabulary fields)::

    fingerprint/   config, road, layout          int64: what the state belongs to
    env/           time, steps, done, seed, rng, road_steps, class_params,
                   controlled (entity slots of env.controlled_vehicles),
                   action_vehicle, observer_vehicle, last_action, features_range...,
                   lane, lanes, trajectory (lane-keeping / racetrack extras)
    wrappers/      elapsed_steps (TimeLimit), has_reset (OrderEnforcing)
    entities/      kind [M]: -1 empty slot, 0 in road.vehicles, 1 in road.objects
                   class_id [M], present [M, F], is_none [M, F]
                   one entry per field of the vocabulary (highway_schema.FIELDS)

Road objects keep their list order (acting and collision checks iterate in that
order). The road network is not stored: it is fixed by the config, so it is
fingerprinted instead and the restoring env's own network is reused.
"""

from __future__ import annotations

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
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs import highway_schema as schema
from torchrl_grpo.envs.codec import StateCodec, as_numpy, check_state_layout, stable_hash
from torchrl_grpo.envs.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    StateMismatchError,
    UnknownFieldError,
)
from torchrl_grpo.envs.gym_state import (
    RNG_WORDS,
    decode_rng,
    encode_rng,
    encode_wrappers,
    restore_wrappers,
    wrapper_spec,
)

_NONE = -1  # encodes None in int slots (lane ids, references, counters)
# Name-mangled private attributes of highway-env's action / observation types.
_ACTION_VEHICLE = "_ActionType__controlled_vehicle"
_OBSERVER = "_ObservationType__observer_vehicle"

# Attributes of the unwrapped env that are fixed by the config or render-only.
_ENV_STATIC = frozenset({
    "_np_random", "_np_random_seed", "_record_video_wrapper", "action_space", "action_type",
    "config", "controlled_vehicles", "done", "enable_auto_render", "observation_space",
    "observation_type", "observation_type_parking", "render_mode", "road", "spec", "steps",
    "time", "viewer", "interval_trajectory", "lpv", "lane", "lanes", "trajectory",
})


class HighwayStateCodec(StateCodec):
    """Snapshots every highway-env scenario into tensors, exactly.

    Args:
        max_vehicles: slots for ``road.vehicles``; defaults to the count after the
            first reset plus 16 (intersection-v0 spawns vehicles as it runs).
        max_objects: slots for ``road.objects``; defaults to the count plus 4.
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
        self.fields = dict(schema.FIELDS)
        self.field_names = list(self.fields)
        self.field_index = {name: i for i, name in enumerate(self.field_names)}
        self.classes = list(schema.VEHICLE_CLASSES)
        self.class_index = {cls: i for i, cls in enumerate(self.classes)}
        self.class_parameters = list(schema.CLASS_PARAMETERS)
        n_vehicles, n_objects = len(road.vehicles), len(road.objects)
        self.max_vehicles = self._max_vehicles or n_vehicles + 16
        self.max_objects = self._max_objects or n_objects + 4
        self.capacity = self.max_vehicles + self.max_objects
        self.n_controlled = len(core.controlled_vehicles)
        self.nodes = sorted(_road_nodes(road.network), key=repr)
        self.node_index = {node: i for i, node in enumerate(self.nodes)}
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
        self.grayscale_shape = obs_type.shape if isinstance(obs_type, GrayscaleObservation) else None
        self.fingerprints = {
            "config": stable_hash(core.spec.id if core.spec else type(core).__name__, core.config),
            "road": stable_hash(_describe(road.network)),
            "layout": stable_hash(
                [(n, f.kind, f.shape, f.choices) for n, f in self.fields.items()],
                [f"{c.__module__}.{c.__qualname__}" for c in self.classes],
                [f"{c.__qualname__}.{n}" for c, n in self.class_parameters],
                self.max_vehicles, self.max_objects, self.max_trajectory, self.n_controlled,
            ),
        }
        self._spec = self._build_spec()
        self._bound = True

    def fingerprint(self, env: gym.Env) -> int:
        """A hash of the config, the road network and the state layout."""
        return stable_hash(self.fingerprints)

    def state_spec(self) -> Composite:
        """See :meth:`StateCodec.state_spec`."""
        return self._spec.clone()

    def _build_spec(self) -> Composite:
        m, n_fields = self.capacity, len(self.field_names)

        def u(shape: tuple[int, ...], dtype: torch.dtype) -> Unbounded:
            return Unbounded(shape, dtype=dtype)

        entities = {
            "kind": u((m,), torch.int64),
            "class_id": u((m,), torch.int64),
            "present": u((m, n_fields), torch.bool),
            "is_none": u((m, n_fields), torch.bool),
        }
        for name, field in self.fields.items():
            for key, (shape, dtype) in _field_columns(name, field).items():
                entities[key] = u((m, *shape), dtype)
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
        core = env.unwrapped
        road = core.road
        entities = road.vehicles + road.objects
        if len(road.vehicles) > self.max_vehicles or len(road.objects) > self.max_objects:
            raise StateCapacityError(
                f"the road holds {len(road.vehicles)} vehicles and {len(road.objects)} objects; "
                f"this env's state pads to {self.max_vehicles} and {self.max_objects}. "
                "Build the env with a larger max_vehicles / max_objects."
            )
        slot = {id(obj): i for i, obj in enumerate(road.vehicles)}
        slot.update({id(obj): self.max_vehicles + i for i, obj in enumerate(road.objects)})
        cols = _Columns(self)
        for obj, i in zip(entities, (slot[id(o)] for o in entities), strict=True):
            self._encode_entity(obj, i, cols, slot)
        arrays = cols.arrays
        arrays.update(self._encode_env(env, slot))
        for key, value in self.fingerprints.items():
            arrays[("fingerprint", key)] = np.asarray(value, dtype=np.int64)
        for key, value in encode_wrappers(env).items():
            arrays[("wrappers", key)] = value
        return TensorDict(
            {k: torch.from_numpy(v) for k, v in arrays.items()}, batch_size=()
        )

    def _encode_entity(self, obj: Any, i: int, cols: _Columns, slot: dict[int, int]) -> None:
        cls = type(obj)
        class_id = self.class_index.get(cls)
        if class_id is None:
            raise UnknownFieldError(
                f"road object class {cls.__module__}.{cls.__qualname__} is not registered; "
                "call torchrl_grpo.envs.register_vehicle_class before building the env"
            )
        cols.kind[i] = 1 if i >= self.max_vehicles else 0
        cols.class_id[i] = class_id
        for name, value in vars(obj).items():
            index = self.field_index.get(name)
            if index is None:
                if name in schema.DERIVED_ATTRIBUTES:
                    continue
                raise UnknownFieldError(
                    f"{cls.__qualname__}.{name} is not a field the highway codec knows "
                    f"(value {value!r}); register it with "
                    "register_vehicle_class(cls, fields={...})"
                )
            cols.present[i, index] = True
            if value is None:
                cols.is_none[i, index] = True
                continue
            try:
                cols.write(name, self.fields[name], i, value, slot)
            except (TypeError, ValueError, KeyError, IndexError) as err:
                raise UnknownFieldError(
                    f"{cls.__qualname__}.{name} holds {value!r}, which does not fit its "
                    f"registered kind {self.fields[name]}: {err}"
                ) from err

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
        put("action_vehicle", _NONE if action_vehicle is None else slot[id(action_vehicle)], np.int64)
        put("observer_vehicle", _NONE if observer is None else slot[id(observer)], np.int64)
        put("last_action", core.action_type.last_action if self.continuous_action else [], np.float64)
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
            lane[:] = self._lane_code(_lane_index_of(core.road.network, core.lane))
        out[("env", "lane")] = lane
        lanes = np.zeros((4, 3), dtype=np.int64)
        lane_list = core.lanes if self.has_lanes else []
        for j, each in enumerate(lane_list):
            lanes[j] = self._lane_code(_lane_index_of(core.road.network, each))
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

    def _lane_code(self, lane_index: tuple | None) -> list[int]:
        if lane_index is None:
            return [_NONE, _NONE, _NONE]
        start, end, lane_id = lane_index
        return [
            self.node_index[start],
            self.node_index[end],
            _NONE if lane_id is None else int(lane_id),
        ]

    # ------------------------------------------------------------------ decode
    def decode(self, env: gym.Env, state: TensorDictBase) -> None:
        """See :meth:`StateCodec.decode`."""
        self._check_bound()
        check_state_layout(state, self._spec)
        for key, expected in self.fingerprints.items():
            found = int(state["fingerprint", key])
            if found != expected:
                what = {
                    "config": "another scenario or config",
                    "road": "another road network",
                    "layout": "an env with another state layout (padding or registered classes)",
                }[key]
                raise StateMismatchError(
                    f"the state was captured from {what}: fingerprint.{key} is {found}, "
                    f"this env's is {expected}"
                )
        core = env.unwrapped
        arrays = as_numpy(state)
        vehicles, objects, by_slot = self._decode_entities(core, arrays)
        plan = self._decode_env(core, arrays, by_slot)
        # Everything is built and validated: from here on nothing can fail.
        road = core.road
        road.vehicles[:] = vehicles
        road.objects[:] = objects
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
        restore_wrappers(
            env, int(arrays["wrappers.elapsed_steps"]), bool(arrays["wrappers.has_reset"])
        )

    def _decode_entities(self, core: Any, a: dict[str, np.ndarray]) -> tuple[list, list, dict]:
        kind = a["entities.kind"]
        class_id = a["entities.class_id"]
        present, is_none = a["entities.present"], a["entities.is_none"]
        if ((kind < -1) | (kind > 1)).any():
            raise StateCorruptedError("entities.kind must be -1, 0 or 1")
        if (kind[: self.max_vehicles] == 1).any() or (kind[self.max_vehicles :] == 0).any():
            raise StateCorruptedError("entities.kind does not match the vehicle / object slots")
        used = np.flatnonzero(kind >= 0)
        if ((class_id[used] < 0) | (class_id[used] >= len(self.classes))).any():
            raise StateCorruptedError(f"entities.class_id outside [0, {len(self.classes)})")
        readers = _Readers(self, core, a)
        built: dict[int, Any] = {}
        refs: list[tuple[Any, str, int]] = []
        for i in used:
            cls = self.classes[class_id[i]]
            obj = cls.__new__(cls)
            d = obj.__dict__
            for f in np.flatnonzero(present[i]):
                name = self.field_names[f]
                if is_none[i, f]:
                    d[name] = None
                elif self.fields[name].kind == "ref":
                    refs.append((obj, name, int(a[f"entities.{name}"][i])))
                else:
                    d[name] = readers.read(name, self.fields[name], i)
            self._rebuild_derived(core, obj, cls, i)
            built[int(i)] = obj
        for obj, name, target in refs:
            if target not in built:
                raise StateCorruptedError(f"entities.{name} refers to empty slot {target}")
            obj.__dict__[name] = built[target]
        vehicles = [built[i] for i in sorted(built) if i < self.max_vehicles]
        objects = [built[i] for i in sorted(built) if i >= self.max_vehicles]
        return vehicles, objects, built

    def _rebuild_derived(self, core: Any, obj: Any, cls: type, i: int) -> None:
        d = obj.__dict__
        d["road"] = core.road
        lane_index = d.get("lane_index")
        try:
            d["lane"] = None if lane_index is None else core.road.network.get_lane(lane_index)
        except (KeyError, IndexError) as err:
            raise StateCorruptedError(
                f"entity slot {i}: lane {lane_index} is not on this road"
            ) from err
        if hasattr(cls, "HISTORY_SIZE"):
            d["log"] = []
            d["history"] = deque(maxlen=cls.HISTORY_SIZE)
        if "position" in d and not np.isfinite(d["position"]).all():
            raise StateCorruptedError(f"entity slot {i}: non-finite position {d['position']}")

    def _decode_env(self, core: Any, a: dict[str, np.ndarray], by_slot: dict) -> dict:
        def vehicle_at(code: int, what: str) -> Any:
            if code == _NONE:
                return None
            if code not in by_slot:
                raise StateCorruptedError(f"env.{what} refers to empty slot {code}")
            return by_slot[code]

        plan: dict[str, Any] = {
            "time": float(a["env.time"]),
            "steps": int(a["env.steps"]),
            "done": bool(a["env.done"]),
            "seed": None if a["env.seed"] < 0 else int(a["env.seed"]),
            "rng": decode_rng(a["env.rng"]),
            "road_steps": None if a["env.road_steps"] < 0 else int(a["env.road_steps"]),
            "class_params": [float(x) for x in a["env.class_params"]],
            "controlled": [vehicle_at(int(c), "controlled") for c in a["env.controlled"]],
            "action_vehicle": vehicle_at(int(a["env.action_vehicle"]), "action_vehicle"),
            "observer_vehicle": vehicle_at(int(a["env.observer_vehicle"]), "observer_vehicle"),
            "last_action": a["env.last_action"].copy(),
        }
        if None in plan["controlled"]:
            raise StateCorruptedError("env.controlled holds an empty slot")
        if not np.isfinite(plan["time"]):
            raise StateCorruptedError(f"env.time is {plan['time']}")
        mask = a["env.features_range_mask"]
        plan["features_range"] = (
            {k: list(map(float, r)) for k, r, m in zip(self.range_keys, a["env.features_range"], mask, strict=True) if m}
            or None
        )
        readers = _Readers(self, core, a)
        lane_code = a["env.lane"]
        plan["lane"] = None if lane_code[0] == _NONE - 1 else readers.lane_object(lane_code, "env.lane")
        n_lanes = int(a["env.lanes_len"])
        if not 0 <= n_lanes <= 4:
            raise StateCorruptedError(f"env.lanes_len is {n_lanes}")
        plan["lanes"] = [readers.lane_object(c, "env.lanes") for c in a["env.lanes"][:n_lanes]]
        n_points = int(a["env.trajectory_len"])
        if not 0 <= n_points <= len(a["env.trajectory"]):
            raise StateCorruptedError(f"env.trajectory_len is {n_points}")
        plan["trajectory"] = [p.reshape(6, 1).copy() for p in a["env.trajectory"][:n_points]]
        if self.grayscale_shape is not None:
            plan["frames"] = a["env.frames"].copy()
        return plan

    def _check_bound(self) -> None:
        if not self._bound:
            raise SnapshotError("the codec is not bound to an env: call bind(env) first")


def _field_columns(name: str, field: schema.Field) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """The tensors one vocabulary field occupies per entity slot."""
    f64, i64, b = torch.float64, torch.int64, torch.bool
    return {
        "float": {name: ((), f64)},
        "int": {name: ((), i64)},
        "bool": {name: ((), b)},
        "vec2": {name: ((2,), f64)},
        "lane": {name: ((3,), i64)},
        "route": {name: ((schema.MAX_ROUTE, 3), i64), f"{name}_len": ((), i64)},
        "speeds": {
            name: ((schema.MAX_SPEEDS,), f64), f"{name}_len": ((), i64), f"{name}_is_int": ((), b)
        },
        "color": {name: ((schema.MAX_COLOR,), i64), f"{name}_len": ((), i64)},
        "ref": {name: ((), i64)},
        "enum": {name: ((), i64)},
        "action": {name: ((2,), f64)},
        "array": {name: (field.shape, f64)},
    }[field.kind]


class _Columns:
    """numpy buffers for one encode: filled object by object, converted once at the end."""

    def __init__(self, codec: HighwayStateCodec) -> None:
        m, n_fields = codec.capacity, len(codec.field_names)
        self.codec = codec
        self.kind = np.full(m, -1, dtype=np.int64)
        self.class_id = np.full(m, -1, dtype=np.int64)
        self.present = np.zeros((m, n_fields), dtype=np.bool_)
        self.is_none = np.zeros((m, n_fields), dtype=np.bool_)
        np_types = {torch.float64: np.float64, torch.int64: np.int64, torch.bool: np.bool_}
        self.columns = {
            key: np.zeros((m, *shape), dtype=np_types[dtype])
            for name, field in codec.fields.items()
            for key, (shape, dtype) in _field_columns(name, field).items()
        }

    @property
    def arrays(self) -> dict[tuple[str, str], np.ndarray]:
        out = {("entities", k): v for k, v in self.columns.items()}
        out[("entities", "kind")] = self.kind
        out[("entities", "class_id")] = self.class_id
        out[("entities", "present")] = self.present
        out[("entities", "is_none")] = self.is_none
        return out

    def write(self, name: str, field: schema.Field, i: int, value: Any, slot: dict) -> None:
        col = self.columns
        kind = field.kind
        if kind in ("float", "int", "bool", "vec2"):
            col[name][i] = value
        elif kind == "action":
            col[name][i] = (value["steering"], value["acceleration"])
        elif kind == "lane":
            col[name][i] = self.codec._lane_code(value)
        elif kind == "route":
            if len(value) > schema.MAX_ROUTE:
                raise StateCapacityError(f"a route of {len(value)} segments (max {schema.MAX_ROUTE})")
            for j, segment in enumerate(value):
                col[name][i, j] = self.codec._lane_code(segment)
            col[f"{name}_len"][i] = len(value)
        elif kind == "speeds":
            value = np.asarray(value)
            if value.ndim != 1 or len(value) > schema.MAX_SPEEDS:
                raise StateCapacityError(f"target speeds of shape {value.shape} (max {schema.MAX_SPEEDS})")
            col[name][i, : len(value)] = value
            col[f"{name}_len"][i] = len(value)
            col[f"{name}_is_int"][i] = np.issubdtype(value.dtype, np.integer)
        elif kind == "color":
            col[name][i, : len(value)] = value
            col[f"{name}_len"][i] = len(value)
        elif kind == "ref":
            col[name][i] = slot[id(value)]
        elif kind == "enum":
            col[name][i] = field.choices.index(value)
        elif kind == "array":
            value = np.asarray(value, dtype=np.float64)
            if value.shape != field.shape:
                raise ValueError(f"shape {value.shape}, expected {field.shape}")
            col[name][i] = value


class _Readers:
    """Turns stored columns back into the Python values highway-env holds."""

    def __init__(self, codec: HighwayStateCodec, core: Any, arrays: dict[str, np.ndarray]) -> None:
        self.codec = codec
        self.core = core
        self.a = arrays

    def lane_index(self, code: np.ndarray, where: str) -> tuple:
        nodes = self.codec.nodes
        if not (0 <= code[0] < len(nodes) and 0 <= code[1] < len(nodes)) or code[2] < _NONE:
            raise StateCorruptedError(f"{where}: lane code {code.tolist()} is not on this road")
        return (nodes[code[0]], nodes[code[1]], None if code[2] == _NONE else int(code[2]))

    def lane_object(self, code: np.ndarray, where: str) -> Any:
        index = self.lane_index(code, where)
        try:
            return self.core.road.network.get_lane(index)
        except (KeyError, IndexError) as err:
            raise StateCorruptedError(f"{where}: lane {index} is not on this road") from err

    def read(self, name: str, field: schema.Field, i: int) -> Any:
        a, kind = self.a, field.kind
        key = f"entities.{name}"
        if kind == "float":
            return float(a[key][i])
        if kind == "int":
            return int(a[key][i])
        if kind == "bool":
            return bool(a[key][i])
        if kind == "vec2" or kind == "array":
            return a[key][i].copy()
        if kind == "action":
            steering, acceleration = a[key][i].tolist()
            return {"steering": steering, "acceleration": acceleration}
        if kind == "lane":
            return self.lane_index(a[key][i], f"{key}[{i}]")
        if kind == "route":
            n = int(a[f"{key}_len"][i])
            if not 0 <= n <= schema.MAX_ROUTE:
                raise StateCorruptedError(f"{key}_len[{i}] is {n}")
            return [self.lane_index(c, f"{key}[{i}]") for c in a[key][i, :n]]
        if kind == "speeds":
            n = int(a[f"{key}_len"][i])
            if not 0 <= n <= schema.MAX_SPEEDS:
                raise StateCorruptedError(f"{key}_len[{i}] is {n}")
            values = a[key][i, :n].copy()
            return values.astype(np.int64) if a[f"{key}_is_int"][i] else values
        if kind == "color":
            n = int(a[f"{key}_len"][i])
            if not 0 <= n <= schema.MAX_COLOR:
                raise StateCorruptedError(f"{key}_len[{i}] is {n}")
            return tuple(int(c) for c in a[key][i, :n])
        if kind == "enum":
            code = int(a[key][i])
            if not 0 <= code < len(field.choices):
                raise StateCorruptedError(f"{key}[{i}] is {code}, not one of {field.choices}")
            return field.choices[code]
        raise StateCorruptedError(f"unknown field kind {kind!r} for {name}")


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
