"""merge-v0's bridge to highway-env's states, and its reset draws replayed on the host.

A merge world's rows are ``road.vehicles`` (the ego, the IDM vehicles) then
``road.objects[0]`` (the obstacle); lanes are flat ids of the road's lane order. The
env's generator (``env.np_random``, PCG64) travels in the tensor state's
``highway.rng`` words, and fresh episodes draw from it exactly as
``MergeEnv._make_vehicles`` does (:func:`merge_draws`), so that a world reset from
the words of ``reset(seed=s)`` is highway-env's world of seed ``s``, and the words
after it are the generator's after that reset.

Example:
    >>> from torchrl_grpo.envs import HighwayEnv
    >>> bridge = MergeBridge("merge-v0", {}, 6)
    >>> state = HighwayEnv("merge-v0", seed=3).get_state()
    >>> world, words, seed = bridge.read(state)
    >>> from torchrl_grpo.envs import states_equal
    >>> states_equal(bridge.write(world, 0, words[0], int(seed[0])), state)
    True
"""

from __future__ import annotations

import numpy as np
import torch
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import MDPVehicle
from highway_env.vehicle.objects import Obstacle
from tensordict import TensorDictBase

from torchrl_grpo.envs.core.errors import StateMismatchError
from torchrl_grpo.envs.core.gym_state import decode_rng, encode_rng
from torchrl_grpo.envs.highway.bridge import HighwayBridge, read_vehicle, vehicle_columns, world_of
from torchrl_grpo.envs.highway.lane_constants import lane_keys
from torchrl_grpo.envs.highway.tensor_params import tensor_params
from torchrl_grpo.sim.merge_reset import DRAWS
from torchrl_grpo.sim.state import Vehicles, World

__all__ = ["MergeBridge", "merge_draws", "row_generators"]


def row_generators(words: torch.Tensor, rows: torch.Tensor):
    """``(row, generator)`` for each row of ``rows``, the generator set to that row's words.

    One numpy PCG64 generator, its state replaced row after row (a world's draws are
    replayed on the host as highway-env makes them); read its state back with
    ``encode_rng`` before the next row.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> words = seeded_rng_words(0).unsqueeze(0).repeat(2, 1)
        >>> rows = torch.tensor([False, True])
        >>> [(int(row), round(g.uniform(), 3)) for row, g in row_generators(words, rows)]
        [(1, 0.637)]
    """
    host = words.detach().cpu().numpy()
    generator = np.random.default_rng()
    for row in np.flatnonzero(rows.detach().cpu().numpy()):
        generator.bit_generator.state = decode_rng(host[row], f"highway.rng of row {row}")
        yield row, generator


def merge_draws(words: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The reset draws of the worlds ``rows`` from their generator words, and the words after.

    Replays ``MergeEnv._make_vehicles``' calls on each row's PCG64 state: per highway
    car ``integers(2)``, ``uniform(-5, 5)``, ``uniform(-1, 1)``.

    Args:
        words: ``[B, RNG_WORDS]`` int64 generator states (see ``gym_state.encode_rng``).
        rows: ``[B]`` bool, the worlds to draw for.

    Returns:
        ``([B, 9] float64 draws (zeros outside rows), [B, RNG_WORDS] words after)``.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> draws, _ = merge_draws(seeded_rng_words(0).unsqueeze(0), torch.tensor([True]))
        >>> draws[0, :3].tolist()  # highway-env's seed 0: lane 1, -2.30 m, -0.92 m/s
        [1.0, -2.302132862361297, -0.9180529521276106]
    """
    after = words.detach().cpu().numpy().copy()
    draws = np.zeros((after.shape[0], DRAWS), dtype=np.float64)
    for row, generator in row_generators(words, rows):
        for k in range(DRAWS // 3):
            lane = generator.integers(2)
            draws[row, 3 * k] = float(lane)
            draws[row, 3 * k + 1] = generator.uniform(-5.0, 5.0)
            draws[row, 3 * k + 2] = generator.uniform(-1.0, 1.0)
        encode_rng(generator, after[row])
    device = words.device
    return torch.from_numpy(draws).to(device), torch.from_numpy(after).to(device)


class MergeBridge(HighwayBridge):
    """Converts merge-v0 states row by row through one HighwayEnv of the config.

    Args:
        scenario: ``"merge-v0"``.
        config: the tensor env's config overrides.
        num_vehicles: the rows of a world (the vehicles and the obstacle).

    Example:
        >>> MergeBridge("merge-v0", {}, 6).keys[4]
        ('b', 'c', 2)
    """

    def __init__(self, scenario: str, config: dict, num_vehicles: int) -> None:
        super().__init__(scenario, config, num_vehicles)
        self.params = tensor_params(scenario, config)
        self.keys = lane_keys(self.env.gym_env.unwrapped.road.network)

    def _check(self, core) -> None:
        vehicles, objects = core.road.vehicles, core.road.objects
        t = self.params.traffic
        fits = (
            len(vehicles) + len(objects) == self.num_vehicles
            and len(objects) == 1
            and type(objects[0]) is Obstacle
            and type(vehicles[0]) is MDPVehicle
            and vehicles[0] is core.vehicle
            and all(type(v) is IDMVehicle and v.enable_lane_change for v in vehicles[1:])
            and all(not v.route for v in vehicles)
        )
        if not fits:
            raise StateMismatchError(
                "the tensor simulator's merge-v0 needs the ego (MDPVehicle), "
                f"{t.vehicles_count} IDMVehicles without routes and the obstacle"
            )
        o = objects[0]
        if (o.position[0], o.position[1], o.heading, o.speed) != (t.obstacle_x, t.obstacle_y, 0, 0):
            raise StateMismatchError("the merge obstacle has moved: the simulator keeps it still")
        fixed = dict(self.params.observation.features_range)
        ranges = core.observation_type.features_range or {}
        if {k: (float(a), float(b)) for k, (a, b) in ranges.items()} != fixed:
            raise StateMismatchError(
                f"the observation's features_range is {ranges}, the simulator's {fixed}"
            )

    def _write_more(self, core, world: World, row: int) -> None:
        """What a scenario's world holds beyond the vehicle table (the roundabout's routes)."""

    def read(self, state: TensorDictBase) -> tuple[World, torch.Tensor, torch.Tensor]:
        """One merge-v0 HighwayEnv state as a float64 world ``[1]``, its generator words and seed.

        Raises:
            SnapshotError: the state does not fit this config, or holds other vehicles,
                routes, a moved obstacle or another observation range.
        """
        self.env.set_state(state)
        core = self.env.gym_env.unwrapped
        self._check(core)
        entities = [*core.road.vehicles, *core.road.objects]
        columns = vehicle_columns(len(entities))
        flat = {key: i for i, key in enumerate(self.keys)}
        for k, v in enumerate(entities):
            lane = flat[tuple(v.lane_index[:2]) + (int(v.lane_index[2]),)]
            if k >= len(core.road.vehicles):  # the obstacle: no target, commands, impact
                columns["x"][k], columns["y"][k] = v.position
                columns["heading"][k], columns["speed"][k] = v.heading, v.speed
                columns["crashed"][k], columns["check_collisions"][k] = (
                    v.crashed,
                    v.check_collisions,
                )
                columns["present"][k] = True
                columns["lane"][k] = columns["target_lane"][k] = lane
                continue
            read_vehicle(v, k, columns, other=k > 0)
            target = v.target_lane_index
            columns["lane"][k] = lane
            columns["target_lane"][k] = flat[tuple(target[:2]) + (int(target[2]),)]
        words = state.get(("sim", "env", "rng")).reshape(1, -1)
        world = world_of(columns, core, words)
        return world, words, state.get(("sim", "env", "seed")).reshape(1)

    def write(self, world: World, row: int, words: torch.Tensor, seed: int) -> TensorDictBase:
        """World row ``row`` (float64, on the CPU) as a merge-v0 HighwayEnv state."""
        self.env.set_state(self.template)
        core = self.env.gym_env.unwrapped
        network = core.road.network
        columns = {name: getattr(world.vehicles, name)[row].tolist() for name in Vehicles._fields}
        entities = [*core.road.vehicles, *core.road.objects]
        for k, v in enumerate(entities):
            value = {name: column[k] for name, column in columns.items()}
            v.lane_index = self.keys[int(value["lane"])]
            v.lane = network.get_lane(v.lane_index)
            v.crashed = bool(value["crashed"])
            if k >= len(core.road.vehicles):
                continue  # the obstacle keeps its template position, heading and speed
            v.position = np.array([value["x"], value["y"]], dtype=np.float64)
            v.heading, v.speed = value["heading"], value["speed"]
            v.target_speed = value["target_speed"]
            v.action = {"steering": value["steering"], "acceleration": value["acceleration"]}
            if k:
                v.timer = value["timer"]
                # merge-v0 keeps IDM's class exponent: an instance one only where it differs.
                if value["delta"] != type(v).DELTA:
                    v.DELTA = value["delta"]
            v.impact = np.array([value["impact_x"], value["impact_y"]]) if value["impact"] else None
            v.target_lane_index = self.keys[int(value["target_lane"])]
            v.check_collisions = bool(value["check_collisions"])
        self._write_more(core, world, row)
        return self._finish_write(core, world, row, words, seed)
