"""The bridge between HighwayEnv states (highway-env's own objects) and tensor worlds.

A :class:`HighwayBridge` owns one :class:`~torchrl_grpo.envs.HighwayEnv` of the tensor
env's scenario and config. It imports a HighwayEnv state by restoring it there and
reading every vehicle's attributes into a float64 world row (:meth:`read`), and exports
a world row by restoring a template state of the config, writing the row into its
vehicles, and taking the state (:meth:`write`). Both go through highway-env's own
objects, so a round trip from highway-env through a tensor world and back gives the
same HighwayEnv state bit for bit, its generator included. Used by
:class:`~torchrl_grpo.envs.TensorHighwayEnv` (``state_from_highway``,
``state_to_highway``, ``render_frames``) and the parity ladder.
"""

from __future__ import annotations

import numpy as np
import torch
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import MDPVehicle
from tensordict import TensorDict, TensorDictBase

from torchrl_grpo.envs.core.errors import StateMismatchError
from torchrl_grpo.envs.core.gym_state import restore_rng
from torchrl_grpo.envs.highway.wrapper import HighwayEnv
from torchrl_grpo.sim.rng import mix64
from torchrl_grpo.sim.state import (
    BOOL_FIELDS,
    FLOAT_FIELDS,
    INT_FIELDS,
    Vehicles,
    World,
    map_world,
    world_from_tensordict,
    world_to_tensordict,
)

__all__ = [
    "HighwayBridge",
    "export_states",
    "import_states",
    "read_vehicle",
    "vehicle_columns",
    "world_of",
]


def vehicle_columns(n: int) -> dict[str, np.ndarray]:
    """Zeroed numpy columns of an ``n``-row vehicle table, by field (dtypes of the state).

    Example:
        >>> vehicle_columns(3)["lane"].dtype, vehicle_columns(3)["present"].any()
        (dtype('int64'), np.False_)
    """
    return (
        {k: np.zeros(n) for k in FLOAT_FIELDS}
        | {k: np.zeros(n, dtype=np.int64) for k in INT_FIELDS}
        | {k: np.zeros(n, dtype=bool) for k in BOOL_FIELDS}
    )


def read_vehicle(v, k: int, columns: dict[str, np.ndarray], other: bool) -> None:
    """A highway-env vehicle's fields into row ``k`` of ``columns``, its lanes aside.

    ``other``: an IDM vehicle (the ego has no MOBIL timer and no IDM exponent).

    Example:
        >>> hw = HighwayEnv("highway-fast-v0", seed=0)
        >>> columns = vehicle_columns(1)
        >>> read_vehicle(hw.gym_env.unwrapped.vehicle, 0, columns, other=False)
        >>> bool(columns["present"][0]), float(columns["speed"][0])
        (True, 25.0)
    """
    columns["x"][k], columns["y"][k] = v.position
    columns["heading"][k], columns["speed"][k] = v.heading, v.speed
    columns["target_speed"][k] = v.target_speed
    columns["steering"][k] = v.action["steering"]
    columns["acceleration"][k] = v.action["acceleration"]
    if other:
        columns["timer"][k], columns["delta"][k] = v.timer, v.DELTA
    if v.impact is not None:
        columns["impact"][k] = True
        columns["impact_x"][k], columns["impact_y"][k] = v.impact
    columns["crashed"][k], columns["check_collisions"][k] = v.crashed, v.check_collisions
    columns["present"][k] = True


def world_of(columns: dict[str, np.ndarray], core, words: torch.Tensor, **more) -> World:
    """The float64 world ``[1]`` of read columns, the reset env ``core``'s clock and words.

    Example:
        >>> hw = HighwayEnv("highway-fast-v0", seed=0)
        >>> words = hw.get_state()["sim", "env", "rng"].reshape(1, -1)
        >>> world_of(vehicle_columns(2), hw.gym_env.unwrapped, words).steps.tolist()
        [0]
    """
    table = {k: torch.from_numpy(a).unsqueeze(0) for k, a in columns.items()}
    return World(
        vehicles=Vehicles(**table),
        speed_index=torch.tensor([int(core.vehicle.speed_index)]),
        time=torch.tensor([float(core.time)], dtype=torch.float64),
        steps=torch.tensor([int(core.steps)]),
        # A stream of its own per imported world, derived from its generator words.
        rng_key=mix64((words * torch.arange(1, words.shape[1] + 1)).sum(-1)),
        rng_counter=torch.zeros(1, dtype=torch.int64),
        **more,
    )


class HighwayBridge:
    """Converts states row by row through one HighwayEnv of a scenario and config.

    Args:
        scenario: ``"highway-v0"`` or ``"highway-fast-v0"``.
        config: the config overrides of the tensor env.
        num_vehicles: the vehicles of a world (the ego and the others).

    Example:
        >>> bridge = HighwayBridge("highway-fast-v0", {}, 21)
        >>> hw = HighwayEnv("highway-fast-v0", seed=3)
        >>> state = hw.get_state()
        >>> world, words, seed = bridge.read(state)
        >>> from torchrl_grpo.envs import states_equal
        >>> states_equal(bridge.write(world, 0, words[0], int(seed[0])), state)
        True
    """

    def __init__(self, scenario: str, config: dict, num_vehicles: int) -> None:
        self.scenario, self.config = scenario, config
        self.env = HighwayEnv(scenario, config, seed=0)
        self.env.reset()
        self.template = self.env.get_state()
        self.num_vehicles = num_vehicles
        self._renderer: HighwayEnv | None = None

    @property
    def renderer(self) -> HighwayEnv:
        """A HighwayEnv that renders RGB frames, headless (built on first use)."""
        if self._renderer is None:
            self._renderer = HighwayEnv(self.scenario, self.config, seed=0, render_mode="rgb_array")
        return self._renderer

    def read(self, state: TensorDictBase) -> tuple[World, torch.Tensor, torch.Tensor]:
        """One HighwayEnv state as a float64 world ``[1]``, its generator words and seed.

        Raises:
            SnapshotError: the state does not fit this config (from the HighwayEnv's
                own checks), or its vehicles are not the ego and IDM vehicles.
        """
        self.env.set_state(state)
        core = self.env.gym_env.unwrapped
        vehicles = core.road.vehicles
        if len(vehicles) != self.num_vehicles or core.road.objects:
            raise StateMismatchError(
                f"the highway-env state holds {len(vehicles)} vehicles and "
                f"{len(core.road.objects)} objects; this config has {self.num_vehicles} vehicles"
            )
        others_idm = all(type(v) is IDMVehicle for v in vehicles[1:])
        if type(vehicles[0]) is not MDPVehicle or vehicles[0] is not core.vehicle or not others_idm:
            raise StateMismatchError(
                "the tensor simulator needs the ego (MDPVehicle) first and IDMVehicles after it"
            )
        columns = vehicle_columns(len(vehicles))
        for k, v in enumerate(vehicles):
            read_vehicle(v, k, columns, other=k > 0)
            columns["lane"][k], columns["target_lane"][k] = v.lane_index[2], v.target_lane_index[2]
        words = state.get(("sim", "env", "rng")).reshape(1, -1)
        world = world_of(columns, core, words)
        return world, words, state.get(("sim", "env", "seed")).reshape(1)

    def _finish_write(self, core, world: World, row: int, words, seed: int) -> TensorDictBase:
        """The ego's speed index, the clock and the generator of row ``row``; the state."""
        core.vehicle.speed_index = int(world.speed_index[row])
        core.time = float(world.time[row])
        core.steps = int(world.steps[row])
        restore_rng(core.np_random, words.numpy())
        core._np_random_seed = None if seed < 0 else seed
        self.env.refresh_output()
        return self.env.get_state()

    def write(self, world: World, row: int, words: torch.Tensor, seed: int) -> TensorDictBase:
        """World row ``row`` (float64, on the CPU) as a HighwayEnv state."""
        self.env.set_state(self.template)
        core = self.env.gym_env.unwrapped
        network = core.road.network
        columns = {name: getattr(world.vehicles, name)[row].tolist() for name in Vehicles._fields}
        for k, v in enumerate(core.road.vehicles):
            value = {name: column[k] for name, column in columns.items()}
            v.position = np.array([value["x"], value["y"]], dtype=np.float64)
            v.heading, v.speed, v.target_speed = (
                value["heading"],
                value["speed"],
                value["target_speed"],
            )
            v.action = {"steering": value["steering"], "acceleration": value["acceleration"]}
            if k:
                v.timer, v.DELTA = value["timer"], value["delta"]
            v.impact = np.array([value["impact_x"], value["impact_y"]]) if value["impact"] else None
            v.lane_index = ("0", "1", int(value["lane"]))
            v.lane = network.get_lane(v.lane_index)
            v.target_lane_index = ("0", "1", int(value["target_lane"]))
            v.crashed, v.check_collisions = bool(value["crashed"]), bool(value["check_collisions"])
        return self._finish_write(core, world, row, words, seed)


def import_states(
    bridge: HighwayBridge,
    states: TensorDictBase,
    dtype: torch.dtype = torch.float64,
    fingerprint: int = 0,
) -> TensorDict:
    """HighwayEnv states ``[M]`` as one tensor state ``[M]``: the world, its ``highway`` words.

    The world is read in float64; its float columns are cast to ``dtype``, and
    ``fingerprint`` is the tensor env's.

    Example:
        >>> hw = HighwayEnv("highway-fast-v0", seed=3)
        >>> state = import_states(HighwayBridge("highway-fast-v0", {}, 21),
        ...                       torch.stack([hw.get_state()] * 2))
        >>> state["vehicles", "x"].shape, state["highway", "rng"].shape
        (torch.Size([2, 21]), torch.Size([2, 10]))
    """
    rows = [bridge.read(states[i]) for i in range(states.shape[0])]
    world = map_world(lambda *columns: torch.cat(columns), *(w for w, _, _ in rows))
    td = world_to_tensordict(world)
    for name in FLOAT_FIELDS:
        td.set(("vehicles", name), td.get(("vehicles", name)).to(dtype))
    words = TensorDict(
        rng=torch.cat([r[1] for r in rows]),
        seed=torch.cat([r[2] for r in rows]),
        batch_size=[len(rows)],
    )
    td.set("highway", words)
    td.set("fingerprint", torch.full(td.batch_size, fingerprint, dtype=torch.int64))
    return td


def export_states(bridge: HighwayBridge, state: TensorDictBase) -> TensorDict:
    """Tensor states ``[M]`` (any float dtype, any device) as HighwayEnv states ``[M]``.

    Example:
        >>> hw = HighwayEnv("highway-fast-v0", seed=3)
        >>> bridge = HighwayBridge("highway-fast-v0", {}, 21)
        >>> state = import_states(bridge, hw.get_state().unsqueeze(0))
        >>> export_states(bridge, state).batch_size
        torch.Size([1])
    """
    state = state.to("cpu")
    world = world_from_tensordict(state)
    as_double = (t.double() if t.is_floating_point() else t for t in world.vehicles)
    world = world._replace(vehicles=Vehicles(*as_double))
    words, seeds = state.get(("highway", "rng")), state.get(("highway", "seed"))
    rows = range(state.shape[0])
    return torch.stack([bridge.write(world, i, words[i], int(seeds[i])) for i in rows])
