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

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from highway_env.envs.common.observation import (
    MultiAgentObservation,
    TupleObservation,
)
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded

from torchrl_grpo.envs.core.bits import (
    bits_spec,
    check_state_layout,
    nested_tensordict,
    spec_layout,
)
from torchrl_grpo.envs.core.codec_registry import register_codec
from torchrl_grpo.envs.core.errors import (
    SnapshotError,
    StateCapacityError,
    StateCorruptedError,
    StateMismatchError,
)
from torchrl_grpo.envs.core.gym_state import (
    check_wrappers,
    encode_wrappers,
    with_seeded_rng,
    wrapper_spec,
)
from torchrl_grpo.envs.core.state_codec import StateCodec, stable_hash
from torchrl_grpo.envs.highway import schema
from torchrl_grpo.envs.highway.entities import decode_entities
from torchrl_grpo.envs.highway.env_fields import EnvFields
from torchrl_grpo.envs.highway.layout import OBJECT, VEHICLE, EntityLayout
from torchrl_grpo.envs.highway.layout_decode import EntityDecoder
from torchrl_grpo.envs.highway.layout_encode import EntityEncoder

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
        """Fix the layout from a freshly reset env: capacities, vocabulary, node names.

        The env's road objects are encoded once, so that a class or an attribute the
        layout cannot store raises :class:`~torchrl_grpo.envs.UnknownFieldError` here,
        when the env is built, and not at its first snapshot.
        """
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
        nodes = sorted(_road_nodes(road.network), key=repr)
        speeds = [len(v.target_speeds) for v in road.vehicles if hasattr(v, "target_speeds")]
        self.layout = EntityLayout(
            schema.FIELDS,
            capacity=self.max_vehicles + self.max_objects,
            nodes=nodes,
            # A planned route is a shortest path: it visits each node at most once.
            max_route=min(16, len(nodes)),
            max_speeds=max(speeds, default=0),
            required=schema.required_fields,
            not_none=schema.not_nullable_fields(),
            lanes={
                (a, b): len(lanes)
                for a, destinations in road.network.graph.items()
                for b, lanes in destinations.items()
            },
            max_magnitude=schema.MAX_MAGNITUDE,
            domains=schema.FIELD_DOMAINS,
        )
        self.encoder = EntityEncoder(self.layout)
        self.decoder = EntityDecoder(self.layout)
        self._history_sizes: dict[type, int | None] = {}
        self.env_fields = EnvFields(env, self.layout, self.class_parameters, self._max_trajectory)
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
                self.env_fields.max_trajectory,
                self.env_fields.n_controlled,
            ),
        }
        self._spec, float_keys = bits_spec(self._build_spec())
        self._float_keys = {_dotted(k) for k in float_keys}
        self._spec_layout = spec_layout(self._spec)
        self._bound = True
        # Fail now, not at the first snapshot, on what the layout cannot store: an
        # unregistered class, or an attribute outside the field vocabulary (named with
        # its class). A road too large for the padding fails at the snapshot, so its
        # objects are checked by name only.
        if len(road.vehicles) <= self.max_vehicles and len(road.objects) <= self.max_objects:
            self.encode(env)
        else:
            self.encoder.check_names([*road.vehicles, *road.objects], self.class_index)

    def fingerprint(self, env: gym.Env) -> int:
        """A hash of the config, the road network and the state layout."""
        return stable_hash(self.fingerprints)

    def state_spec(self) -> Composite:
        """See :meth:`StateCodec.state_spec`."""
        return self._spec.clone()

    def _build_spec(self) -> Composite:
        def u(shape: tuple[int, ...], dtype: torch.dtype) -> Unbounded:
            return Unbounded(shape, dtype=dtype)

        env = self.env_fields.spec()
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
            ("entities", k): v for k, v in self.encoder.encode(items, self.class_index).items()
        }
        arrays.update(self.env_fields.encode(env, slot))
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
        vehicles, objects, by_slot = decode_entities(
            self.decoder, self.classes, core, blocks, self.max_vehicles, self._history_sizes
        )
        plan = self.env_fields.decode(core, found, by_slot)
        plan["vehicles"], plan["objects"] = vehicles, objects
        plan["wrappers"] = (
            found[("wrappers", "elapsed_steps")].item(),
            found[("wrappers", "has_reset")].item(),
        )
        check_wrappers(*plan["wrappers"])
        return plan

    def _commit(self, env: gym.Env, plan: dict[str, Any]) -> None:
        # Everything is built and validated: from here on nothing can fail.
        road = env.unwrapped.road
        road.vehicles[:] = plan["vehicles"]
        road.objects[:] = plan["objects"]
        self.env_fields.commit(env, plan)

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
