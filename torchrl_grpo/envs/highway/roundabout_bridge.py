"""roundabout-v0's bridge to highway-env's states, and its reset draws replayed on the host.

A roundabout world's rows are ``road.vehicles`` (the ego, then the IDM vehicles); lanes
are flat ids of the road's lane order and each vehicle's ``route`` travels as leg codes
(:mod:`torchrl_grpo.sim.routes`). The env's generator (``env.np_random``, PCG64)
travels in the tensor state's ``highway.rng`` words, and fresh episodes draw from it
exactly as ``RoundaboutEnv._make_vehicles`` does (:func:`roundabout_draws`), so that a
world reset from the words of ``reset(seed=s)`` is highway-env's world of seed ``s``.

Example:
    >>> from torchrl_grpo.envs import HighwayEnv, states_equal
    >>> bridge = RoundaboutBridge("roundabout-v0", {}, 5)
    >>> state = HighwayEnv("roundabout-v0", seed=3).get_state()
    >>> world, words, seed = bridge.read(state)
    >>> states_equal(bridge.write(world, 0, words[0], int(seed[0])), state)
    True
"""

from __future__ import annotations

import numpy as np
import torch
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import MDPVehicle
from tensordict import TensorDictBase

from torchrl_grpo.envs.core.errors import StateMismatchError
from torchrl_grpo.envs.core.gym_state import encode_rng
from torchrl_grpo.envs.highway.merge_bridge import MergeBridge, row_generators
from torchrl_grpo.envs.highway.tensor_params import tensor_params
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.roundabout_reset import DRAWS
from torchrl_grpo.sim.state import World

__all__ = ["RoundaboutBridge", "roundabout_draws"]


def roundabout_draws(
    words: torch.Tensor, rows: torch.Tensor, params: RoundaboutParams | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The reset draws of the worlds ``rows`` from their generator words, and the words after.

    Replays ``RoundaboutEnv._make_vehicles``' calls on each row's PCG64 state: per IDM
    vehicle ``normal()``, ``normal()``, ``choice(destinations)``, ``uniform(3.5, 4.5)``.

    Args:
        words: ``[B, RNG_WORDS]`` int64 generator states (see ``gym_state.encode_rng``).
        rows: ``[B]`` bool, the worlds to draw for.
        params: the constants (the destinations, the exponents' range); the default
            config's if ``None``.

    Returns:
        ``([B, 16] float64 draws (zeros outside rows), [B, RNG_WORDS] words after)``.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> draws, _ = roundabout_draws(seeded_rng_words(0).unsqueeze(0), torch.tensor([True]))
        >>> [round(d, 4) for d in draws[0, :4].tolist()]  # seed 0: the incoming car's
        [0.1257, -0.1321, 0.0, 3.5165]
    """
    params = params or tensor_params("roundabout-v0")
    exits = len(params.traffic.destinations)
    low, high = params.idm.delta_range
    after = words.detach().cpu().numpy().copy()
    draws = np.zeros((after.shape[0], DRAWS), dtype=np.float64)
    for row, generator in row_generators(words, rows):
        for k in range(DRAWS // 4):
            draws[row, 4 * k] = generator.normal()
            draws[row, 4 * k + 1] = generator.normal()
            # The draw of Generator.choice(destinations), and the index it picks, 7 times
            # faster (tests/envs/test_reset_draws.py replays choice itself beside it).
            draws[row, 4 * k + 2] = generator.integers(exits)
            draws[row, 4 * k + 3] = generator.uniform(low=low, high=high)
        encode_rng(generator, after[row])
    device = words.device
    return torch.from_numpy(draws).to(device), torch.from_numpy(after).to(device)


class RoundaboutBridge(MergeBridge):
    """Converts roundabout-v0 states row by row through one HighwayEnv of the config.

    Args:
        scenario: ``"roundabout-v0"``.
        config: the tensor env's config overrides.
        num_vehicles: the rows of a world.

    Example:
        >>> RoundaboutBridge("roundabout-v0", {}, 5).keys[20]
        ('ser', 'ses', 0)
    """

    def __init__(self, scenario: str, config: dict, num_vehicles: int) -> None:
        super().__init__(scenario, config, num_vehicles)
        self.roads = list(dict.fromkeys(k[:2] for k in self.keys))

    def _check(self, core) -> None:
        vehicles = core.road.vehicles
        fits = (
            len(vehicles) == self.num_vehicles
            and not core.road.objects
            and type(vehicles[0]) is MDPVehicle
            and vehicles[0] is core.vehicle
            and all(type(v) is IDMVehicle and v.enable_lane_change for v in vehicles[1:])
            and all(v.route is not None for v in vehicles)
        )
        if not fits:
            raise StateMismatchError(
                "the tensor simulator's roundabout-v0 needs the ego (MDPVehicle) and "
                f"{self.num_vehicles - 1} IDMVehicles, each with a route, and no objects"
            )
        length = self.params.road.route_length
        if any(len(v.route) > length for v in vehicles):
            raise StateMismatchError(f"a route longer than the {length} legs the simulator holds")

    def _code(self, leg) -> int:
        _from, _to, _id = leg
        if _id is None:
            return self.params.road.lanes_count + self.roads.index((_from, _to))
        return self.keys.index((_from, _to, int(_id)))

    def _leg(self, code: int) -> tuple:
        road = self.params.road
        if code < road.lanes_count:
            return self.keys[code]
        return (*self.roads[code - road.lanes_count], None)

    def read(self, state: TensorDictBase) -> tuple[World, torch.Tensor, torch.Tensor]:
        """One roundabout-v0 HighwayEnv state as a float64 world ``[1]``, its words and seed.

        Raises:
            SnapshotError: the state does not fit this config, or holds other vehicles,
                objects, or vehicles without routes.
        """
        world, words, seed = super().read(state)
        vehicles = self.env.gym_env.unwrapped.road.vehicles
        route = torch.full((1, len(vehicles), self.params.road.route_length), -1)
        for k, v in enumerate(vehicles):
            for i, leg in enumerate(v.route):
                route[0, k, i] = self._code(leg)
        head = torch.zeros(1, len(vehicles), dtype=torch.int64)
        return world._replace(route=route, route_head=head), words, seed

    def _write_more(self, core, world: World, row: int) -> None:
        legs, heads = world.route[row].tolist(), world.route_head[row].tolist()
        for v, codes, head in zip(core.road.vehicles, legs, heads, strict=True):
            v.route = [self._leg(c) for c in codes[head:] if c >= 0]
            if v is not core.vehicle:  # IDM exponents are drawn per vehicle here
                v.DELTA = float(world.vehicles.delta[row, core.road.vehicles.index(v)])
