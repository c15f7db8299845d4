"""intersection-v0's bridge to highway-env's states, and its draws replayed on the host.

An intersection world's rows are the ego (row 0) and the IDM vehicles in
``road.vehicles`` order, packed, with ``present`` False on the free rows; the ego's
place among them is ``ego_rank`` (highway-env appends the ego after the reset's
vehicles). Lanes are flat ids of the road's lane order; routes travel as leg codes
(:mod:`torchrl_grpo.sim.routes`); each vehicle's ``is_yielding`` as a yield state
(:mod:`torchrl_grpo.sim.regulation`).

The env's generator (``env.np_random``, PCG64) travels in the tensor state's
``highway.rng`` words. Every spawn draws from it as ``_spawn_vehicle`` does
(:func:`spawn_draws`): ``uniform()``, and unless that exceeds the spawn probability
``choice(4, 2, replace=False)``, ``normal()`` twice and, only if the car stays,
``uniform(3.5, 4.5)``. The host cannot know whether the car stays before the tensor
step places it, so it returns the words after both outcomes.

Example:
    >>> from torchrl_grpo.envs import HighwayEnv, states_equal
    >>> bridge = IntersectionBridge("intersection-v0", {}, 24)
    >>> state = HighwayEnv("intersection-v0", seed=3).get_state()
    >>> world, words, seed = bridge.read(state)
    >>> states_equal(bridge.write(world, 0, words[0], int(seed[0])), state)
    True
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch
from highway_env.road.regulation import RegulatedRoad
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import MDPVehicle
from tensordict import TensorDictBase

from torchrl_grpo.envs.core.errors import StateMismatchError
from torchrl_grpo.envs.core.gym_state import check_rng_rows, encode_rng
from torchrl_grpo.envs.highway.bridge import HighwayBridge, read_vehicle, vehicle_columns, world_of
from torchrl_grpo.envs.highway.lane_constants import lane_keys
from torchrl_grpo.envs.highway.merge_bridge import row_generators
from torchrl_grpo.envs.highway.tensor_params import tensor_params
from torchrl_grpo.sim.intersection import FramesFn, tensor_frames, warm_up
from torchrl_grpo.sim.intersection_params import IntersectionParams
from torchrl_grpo.sim.intersection_reset import (
    SPAWN_DRAWS,
    empty_intersection,
    place_ego,
    spawn_vehicles,
)
from torchrl_grpo.sim.regulation import NEVER, YIELDED, YIELDING
from torchrl_grpo.sim.state import Vehicles, World, map_world

__all__ = [
    "HOST_DRAWS",
    "IntersectionBridge",
    "IntersectionDraws",
    "ego_draws",
    "intersection_fresh",
    "spawn_draws",
]


def spawn_draws(
    words: torch.Tensor,
    rows: torch.Tensor,
    params: IntersectionParams,
    probability: float,
    go_straight: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One ``_spawn_vehicle``'s draws for the worlds ``rows``, and the words after it.

    Args:
        words: ``[B, RNG_WORDS]`` int64 generator states.
        rows: ``[B]`` bool, the worlds that spawn.
        params: the constants (the exponents' range).
        probability: the spawn probability.
        go_straight: the challenger's route (straight across).

    Returns:
        ``([B, SPAWN_DRAWS] float64 draws, words if the car is dropped, words if it
        stays)``; outside ``rows`` the draws are 1 (no spawn) and the words unchanged.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> params = tensor_params("intersection-v0")
        >>> words = seeded_rng_words(0).unsqueeze(0)
        >>> draws, dropped, stays = spawn_draws(words, torch.tensor([True]), params, 0.6)
        >>> [round(d, 4) for d in draws[0].tolist()]  # seed 0: 0.637 > 0.6, no spawn
        [0.637, 0.0, 0.0, 0.0, 0.0, 0.0]
        >>> torch.equal(dropped, stays)  # nothing more was drawn
        True
    """
    low, high = params.idm.delta_range
    draws = np.ones((words.shape[0], SPAWN_DRAWS), dtype=np.float64)
    dropped = words.detach().cpu().numpy().copy()
    stays = dropped.copy()
    for row, g in row_generators(words, rows):
        u = g.uniform()
        draws[row] = (u, 0, 0, 0, 0, 0)
        if not u > probability:
            route = g.choice(range(4), size=2, replace=False)
            route[1] = (route[0] + 2) % 4 if go_straight else route[1]
            draws[row, 1:5] = (route[0], route[1], g.normal(), g.normal())
        encode_rng(g, dropped[row])
        if not u > probability:
            draws[row, 5] = g.uniform(low=low, high=high)
        encode_rng(g, stays[row])
    device = words.device
    return (
        torch.from_numpy(draws).to(device),
        torch.from_numpy(dropped).to(device),
        torch.from_numpy(stays).to(device),
    )


def ego_draws(
    words: torch.Tensor, rows: torch.Tensor, params: IntersectionParams
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ego's draws of ``_make_vehicles``: ``(destination index, normal(1.0), words after)``.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> params = tensor_params("intersection-v0")
        >>> words = seeded_rng_words(0).unsqueeze(0)
        >>> goal, offset, _ = ego_draws(words, torch.tensor([True]), params)
        >>> goal.tolist(), round(offset.item(), 4)  # the config's destination, o1
        ([1], 1.1257)
    """
    goal = np.full(words.shape[0], max(params.traffic.ego_destination, 0), dtype=np.int64)
    offset = np.zeros(words.shape[0], dtype=np.float64)
    after = words.detach().cpu().numpy().copy()
    for row, g in row_generators(words, rows):
        if params.traffic.ego_destination < 0:
            goal[row] = int(g.integers(1, 4))
        offset[row] = g.normal(1.0)
        encode_rng(g, after[row])
    device = words.device
    return (
        torch.from_numpy(goal).to(device),
        torch.from_numpy(offset).to(device),
        torch.from_numpy(after).to(device),
    )


class IntersectionDraws(NamedTuple):
    """Who replays intersection-v0's draws: numpy on the host (:data:`HOST_DRAWS`) or C++.

    Attributes:
        spawn: a spawn's draws, as :func:`spawn_draws`.
        ego: the ego's, as :func:`ego_draws`.
    """

    spawn: Callable
    ego: Callable


#: The draws replayed by numpy, a generator per world (the tensor path's: no compiler).
HOST_DRAWS = IntersectionDraws(spawn_draws, ego_draws)


def intersection_fresh(
    world: World,
    rows,
    words,
    seeds,
    params: IntersectionParams,
    frames: FramesFn = tensor_frames,
    draws: IntersectionDraws = HOST_DRAWS,
):
    """Fresh worlds on ``rows`` as ``_make_vehicles`` builds them from the generator words.

    The reset's spawns, its 3 seconds of traffic (run by ``frames``: the tensor path's,
    or the C++ ones), the challenger and the ego, each spawn's draws replayed (by
    ``draws``: numpy's, or the C++ ones) and placed on the device. Returns ``(worlds,
    words after, seeds)``: row ``i`` of words seeded with ``s`` is highway-env's world
    after ``reset(seed=s)``.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> from torchrl_grpo.sim.intersection_reset import empty_intersection
        >>> params = tensor_params("intersection-v0")
        >>> rows, words = torch.tensor([True]), seeded_rng_words(3).unsqueeze(0)
        >>> empty = empty_intersection(1, params)
        >>> world, _, _ = intersection_fresh(empty, rows, words, None, params)
        >>> int(world.vehicles.present.sum()), world.ego_rank.tolist(), world.road_steps.tolist()
        (8, [7], [45])
    """
    index = rows.nonzero().flatten()
    if index.numel() == 0:
        return world, words, seeds
    check_rng_rows(words, rows)  # here, where a bad row's error names its place in the batch
    # Only the rows that reset are built (a few of the batch at each step), then put back.
    old = map_world(lambda t: t.index_select(0, index), world)
    new, drawn = _fresh_worlds(old, words.index_select(0, index), params, frames, draws)
    world = map_world(lambda t, s: t.index_copy(0, index, s), world, new)
    return world, words.index_copy(0, index, drawn), seeds


def _fresh_worlds(old: World, words, params, frames: FramesFn, draws: IntersectionDraws):
    """``(fresh worlds in place of every row of old, words after)``: ``intersection_fresh``'s."""
    t = params.traffic
    v = old.vehicles
    rows = torch.ones(v.x.shape[0], dtype=torch.bool, device=v.x.device)
    new = empty_intersection(v.x.shape[0], params, v.x.dtype, v.x.device)
    new = new._replace(rng_key=old.rng_key, rng_counter=old.rng_counter)

    def spawn(new, longitudinal, position, speed, probability, straight=False):
        drawn, dropped, kept = draws.spawn(words, rows, params, probability, straight)
        new, stayed = spawn_vehicles(new, drawn, longitudinal, position, speed, probability, params)
        return new, torch.where(stayed.unsqueeze(-1), kept, dropped)

    for s in t.spawn_s:
        new, words = spawn(
            new, s, t.position_deviation, t.speed_deviation, t.initial_spawn_probability
        )
    new = warm_up(new, rows, params, frames)
    new, words = spawn(new, t.challenger_s, t.challenger_position_deviation,
                       t.challenger_speed_deviation, 1.0, straight=True)  # fmt: skip
    goal, offset, words = draws.ego(words, rows, params)
    return place_ego(new, rows, goal, offset, params), words


class IntersectionBridge(HighwayBridge):
    """Converts intersection-v0 states row by row through one HighwayEnv of the config.

    Args:
        scenario: ``"intersection-v0"``.
        config: the tensor env's config overrides.
        num_vehicles: the rows of a world.

    Example:
        >>> IntersectionBridge("intersection-v0", {}, 24).keys[2]
        ('ir0', 'il1', 0)
    """

    def __init__(self, scenario: str, config: dict, num_vehicles: int) -> None:
        super().__init__(scenario, config, num_vehicles)
        self.params = tensor_params(scenario, config)
        self.keys = lane_keys(self.env.gym_env.unwrapped.road.network)
        self.flat = {key: i for i, key in enumerate(self.keys)}

    def _check(self, core) -> list:
        vehicles = core.road.vehicles
        others = [v for v in vehicles if v is not core.vehicle]
        fits = (
            not core.road.objects
            and type(core.vehicle) is MDPVehicle
            and core.vehicle in vehicles
            and all(type(v) is IDMVehicle for v in others)
            and all(v.route for v in vehicles)
            and len(others) < self.num_vehicles
        )
        if not fits:
            raise StateMismatchError(
                "the tensor simulator's intersection-v0 needs the ego (MDPVehicle) and at "
                f"most {self.num_vehicles - 1} IDMVehicles, each with a route, and no objects"
            )
        if any(len(v.route) > self.params.route_length for v in vehicles):
            raise StateMismatchError(
                f"a route longer than the {self.params.route_length} legs the simulator holds"
            )
        return others

    def _lane(self, index) -> int:
        return self.flat[(index[0], index[1], int(index[2]))]

    def _code(self, leg) -> int:
        _from, _to, _id = leg
        if _id is None:
            return self.params.road.lanes_count + self.params.road.road[self._lane((_from, _to, 0))]
        return self._lane(leg)

    def _leg(self, code: int) -> tuple:
        road = self.params.road
        if code < road.lanes_count:
            return self.keys[code]
        return (*self.keys[road.road.index(code - road.lanes_count)][:2], None)

    def read(self, state: TensorDictBase) -> tuple[World, torch.Tensor, torch.Tensor]:
        """One intersection-v0 HighwayEnv state as a float64 world ``[1]``, its words and seed.

        Raises:
            SnapshotError: the state does not fit this config, or holds other vehicles,
                objects, too many vehicles or vehicles without routes.
        """
        self.env.set_state(state)
        core = self.env.gym_env.unwrapped
        others = self._check(core)
        n = self.num_vehicles
        columns = vehicle_columns(n)
        route = torch.full((1, n, self.params.route_length), -1)
        yielding = torch.zeros(1, n, dtype=torch.int8)
        for k, v in enumerate([core.vehicle, *others]):
            read_vehicle(v, k, columns, other=k > 0)
            columns["lane"][k] = self._lane(v.lane_index)
            columns["target_lane"][k] = self._lane(v.target_lane_index)
            for i, leg in enumerate(v.route):
                route[0, k, i] = self._code(leg)
            if hasattr(v, "is_yielding"):
                yielding[0, k] = YIELDING if v.is_yielding else YIELDED
        words = state.get(("sim", "env", "rng")).reshape(1, -1)
        world = world_of(
            columns,
            core,
            words,
            route=route,
            route_head=torch.zeros(1, n, dtype=torch.int64),
            yielding=yielding,
            road_steps=torch.tensor([int(core.road.steps)]),
            ego_rank=torch.tensor([core.road.vehicles.index(core.vehicle)]),
        )
        return world, words, state.get(("sim", "env", "seed")).reshape(1)

    def write(self, world: World, row: int, words: torch.Tensor, seed: int) -> TensorDictBase:
        """World row ``row`` (float64, on the CPU) as an intersection-v0 HighwayEnv state."""
        self.env.set_state(self.template)
        core = self.env.gym_env.unwrapped
        road, network = core.road, core.road.network
        columns = {name: getattr(world.vehicles, name)[row].tolist() for name in Vehicles._fields}
        legs, head = world.route[row].tolist(), world.route_head[row].tolist()
        states = world.yielding[row].tolist()
        built = []
        for k in range(self.num_vehicles):
            value = {name: column[k] for name, column in columns.items()}
            if not value["present"]:
                continue
            position = np.array([value["x"], value["y"]], dtype=np.float64)
            v = core.vehicle if k == 0 else IDMVehicle(road, position)
            v.position, v.heading, v.speed = position, value["heading"], value["speed"]
            v.lane_index = self.keys[int(value["lane"])]
            v.lane = network.get_lane(v.lane_index)
            v.target_lane_index = self.keys[int(value["target_lane"])]
            v.target_speed = value["target_speed"]
            v.action = {"steering": value["steering"], "acceleration": value["acceleration"]}
            v.crashed, v.check_collisions = bool(value["crashed"]), bool(value["check_collisions"])
            v.impact = np.array([value["impact_x"], value["impact_y"]]) if value["impact"] else None
            v.route = [self._leg(c) for c in legs[k][head[k] :] if c >= 0]
            if k:
                v.timer, v.DELTA = value["timer"], value["delta"]
            if states[k] != NEVER:
                v.is_yielding, v.yield_timer = states[k] == YIELDING, 0
            if states[k] == YIELDING:  # set with the yield, deleted with its release
                v.color = RegulatedRoad.YIELDING_COLOR
            built.append(v)
        rank = int(world.ego_rank[row])
        road.vehicles = [*built[1 : rank + 1], built[0], *built[rank + 1 :]]
        road.steps = int(world.road_steps[row])
        return self._finish_write(core, world, row, words, seed)
