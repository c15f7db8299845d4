"""The parity ladder: the tensor simulator against highway-env, world by world and step by step.

Four rungs, each a function returning plain numbers (``benchmarks/bench_parity.py``
prints them, the tests assert them):

a. :func:`same_world`: imported worlds give highway-env's observation, reward and flags;
b. :func:`one_step`: from each world, each of the 5 actions: every vehicle after the step;
c. :func:`whole_episodes`: from imported worlds, the same actions to the end;
d. :func:`~.parity_resets.fresh_resets` (with :mod:`.parity_stats`): episode statistics of
   fresh worlds against highway-env's, recorded once by ``scripts/highway_reference.py``.

Worlds are recorded from highway-env runs by :func:`record_worlds` and moved into the
tensor simulator through the bridge (:meth:`TensorHighwayEnv.state_from_highway`);
comparisons are made in float64.

Example:
    >>> from torchrl_grpo.modules import ConstantActionPolicy
    >>> states, kinds = record_worlds("highway-fast-v0", [ConstantActionPolicy(3)], 5, seed=0)
    >>> states.batch_size, kinds["changing"] > 0, kinds["curved"]
    (torch.Size([5]), True, 0)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from gymnasium.spaces import Box
from tensordict import TensorDict, TensorDictBase

from torchrl_grpo.envs.highway.parity_resets import fresh_resets
from torchrl_grpo.envs.highway.wrapper import HighwayEnv
from torchrl_grpo.sim.state import world_from_tensordict

__all__ = [
    "StepMiss",
    "fresh_resets",
    "one_step",
    "record_worlds",
    "same_world",
    "whole_episodes",
]

Policy = Callable[[TensorDictBase], TensorDictBase]
FIELDS = ("x", "y", "heading", "speed", "lane", "target_lane", "crashed")
#: What :func:`record_worlds` counts of its worlds.
KINDS = (
    "changing", "near_miss", "crashed", "curved", "ring", "sine", "forbidden", "hand_over",
    "yielding",
)  # fmt: skip


def record_worlds(
    scenario: str,
    policies: Sequence[Policy],
    count: int,
    *,
    config: dict | None = None,
    seed: int = 0,
    near: float = 8.0,
) -> tuple[TensorDictBase, dict[str, int]]:
    """``count`` HighwayEnv states visited by highway-env episodes of the policies, in turn.

    Every state of an episode is kept, the final one included (crashed worlds), so the
    set holds lane changes in progress and near misses as the policies produce them.

    Returns:
        ``(states [count], counts)``: how many worlds have a lane change in progress
        (``changing``), the ego within ``near`` metres of another vehicle without a
        crash (``near_miss``), a crashed ego (``crashed``), a vehicle on a curved lane
        (``curved``), on a circular lane (``ring``: roundabout-v0's) or a sine lane
        (``sine``: merge-v0's ramp, roundabout-v0's entries and exits), on a forbidden
        lane (``forbidden``: merge-v0's ramp), handing over to another road
        (``hand_over``) or yielding at the intersection (``yielding``).
    """
    env = HighwayEnv(scenario, config)
    states: list[TensorDictBase] = []
    kinds = dict.fromkeys(KINDS, 0)
    episode = 0
    while len(states) < count:
        policy = policies[episode % len(policies)]
        env.set_seed(seed + episode)
        td = env.reset()
        episode += 1
        while len(states) < count:
            states.append(env.get_state())
            _count_kinds(env, kinds, near)
            if bool(td.get("done", torch.zeros(1, dtype=torch.bool))):
                break
            td = env.step(policy(td.exclude("state")))
            td = td.get("next")
    return torch.stack(states), kinds


def _count_kinds(env: HighwayEnv, kinds: dict[str, int], near: float) -> None:
    core = env.gym_env.unwrapped
    vehicles = core.road.vehicles
    ego = core.vehicle
    network = core.road.network
    kinds["changing"] += any(v.lane_index != v.target_lane_index for v in vehicles)
    lanes = [network.get_lane(v.lane_index) for v in vehicles]
    # Curved lanes, the ramp's forbidden lanes and hand-overs between roads (merge-v0).
    kinds["curved"] += any(type(lane).__name__ != "StraightLane" for lane in lanes)
    kinds["ring"] += any(type(lane).__name__ == "CircularLane" for lane in lanes)
    kinds["sine"] += any(type(lane).__name__ == "SineLane" for lane in lanes)
    kinds["forbidden"] += any(lane.forbidden for lane in lanes)
    kinds["hand_over"] += any(v.lane_index[:2] != v.target_lane_index[:2] for v in vehicles)
    kinds["yielding"] += any(getattr(v, "is_yielding", False) for v in vehicles)
    others = [float(np.linalg.norm(v.position - ego.position)) for v in vehicles if v is not ego]
    if ego.crashed:
        kinds["crashed"] += 1
    elif min(others, default=float("inf")) < near:
        kinds["near_miss"] += 1


def _float64_observation(core) -> np.ndarray:
    """highway-env's Kinematics observation before its cast to float32."""
    obs_type = core.observation_type
    space = obs_type.space
    shape = (obs_type.vehicles_count, len(obs_type.features))
    obs_type.space = lambda: Box(-np.inf, np.inf, shape, np.float64)
    try:
        return obs_type.observe()
    finally:
        obs_type.space = space


def same_world(tensor_env, states: TensorDictBase) -> dict[str, float]:
    """Rung a: max |difference| of the observation, reward components and flags.

    ``tensor_env`` is a float64 ``TensorHighwayEnv`` with ``num_envs == len(states)``.
    """
    out = tensor_env.reset(
        TensorDict(state=tensor_env.state_from_highway(states), batch_size=tensor_env.batch_size),
        set_state=True,
    )
    hw = tensor_env.bridge.env
    worst = {"observation": 0.0, "reward": 0.0, "flags": 0}
    for i in range(states.shape[0]):
        hw.set_state(states[i])
        core = hw.gym_env.unwrapped
        obs = torch.from_numpy(_float64_observation(core))
        worst["observation"] = max(
            worst["observation"], float((out["observation"][i] - obs).abs().max())
        )
        parts = core._rewards(None)
        mine = {k: float(out["reward_components", k][i]) for k in parts}
        fresh = core.steps == 0
        for k, v in parts.items():
            ref = 0.0 if fresh else float(v)
            worst["reward"] = max(worst["reward"], abs(mine[k] - ref))
        flags = (bool(out["crashed"][i]), bool(out["on_road"][i]))
        worst["flags"] += flags != (core.vehicle.crashed, core.vehicle.on_road)
    return worst


@dataclass
class StepMiss:
    """A (world, action) pair whose step disagrees with highway-env beyond the tolerance.

    Attributes:
        world: index of the world.
        action: the meta-action.
        vehicle: the first vehicle that disagrees (0: the ego).
        field: the first field that disagrees.
        error: its |difference| (1 for a flag or a lane).
        explanation: the parity hazard it matches.
    """

    world: int
    action: int
    vehicle: int
    field: str
    error: float
    explanation: str = ""


@dataclass
class StepReport:
    """Rung b's result: agreement over (world, action) pairs."""

    pairs: int = 0
    agree: int = 0
    max_error: dict[str, float] = field(
        default_factory=lambda: dict.fromkeys((*FIELDS, "route", "yielding", "present"), 0.0)
    )
    misses: list[StepMiss] = field(default_factory=list)

    @property
    def agreement(self) -> float:
        """Fraction of pairs that agree to the tolerance."""
        return self.agree / max(self.pairs, 1)


def _remaining(route: torch.Tensor, head: torch.Tensor) -> torch.Tensor:
    """``[B, N, R]`` each route's legs from its head on, -1 padded (a read route's head is 0)."""
    length = route.shape[-1]
    at = head.unsqueeze(-1) + torch.arange(length)
    legs = route.gather(-1, at.clamp(max=length - 1))
    return torch.where(at < length, legs, -1)


def _differences(a, b) -> dict[str, torch.Tensor]:
    """Per field, ``[B, N]`` |a - b| (floats) or a != b (lanes, flags, routes) of two worlds.

    Rows free in both worlds (intersection-v0's) are not compared; a row present in one
    only differs in ``present``, as do worlds whose ego sits elsewhere in road order.
    """
    out = {}
    used = a.vehicles.present | b.vehicles.present
    for name in FIELDS:
        x, y = getattr(a.vehicles, name), getattr(b.vehicles, name)
        out[name] = (x.double() - y.double()).abs() if x.is_floating_point() else (x != y).double()
    if a.route is not None:
        legs = _remaining(a.route, a.route_head) != _remaining(b.route, b.route_head)
        out["route"] = legs.any(-1).double()
    if a.yielding is not None:
        out["yielding"] = (a.yielding != b.yielding).double()
        rank = (a.ego_rank != b.ego_rank).unsqueeze(-1)
        out["present"] = ((a.vehicles.present != b.vehicles.present) | rank).double()
    return {k: torch.where(used, d, 0.0) for k, d in out.items()}


def _explain(before, after_hw, after_t, world: int, vehicle: int, name: str) -> str:
    """Name the parity hazard a miss comes from, by what flipped."""
    v_hw, v_t = after_hw.vehicles, after_t.vehicles
    if name == "target_lane" or (
        name in ("x", "y", "heading")
        and v_hw.target_lane[world, vehicle] != v_t.target_lane[world, vehicle]
    ):
        timer = float(before.vehicles.timer[world, vehicle])
        return f"a lane-change decision flipped (MOBIL gain or abort threshold; timer {timer:.6f})"
    if name == "crashed" or v_hw.crashed[world].ne(v_t.crashed[world]).any():
        return "a collision test flipped at the tolerance of the separating-axis test"
    if name == "lane":
        return "the closest-lane argmin flipped between two lanes"
    if name == "route":
        return "a route's leg was dropped on one side only (after_end at the lane's end)"
    if name == "yielding":
        return "a conflict test flipped (predicted rectangles touching at the tolerance)"
    if name == "present":
        return "a spawn's 15 m clearance or an exit's margin flipped"
    return "float rounding (transcendental functions of torch and libm differ by an ulp)"


def one_step(
    tensor_env,
    states: TensorDictBase,
    tolerance: float = 1e-6,
    actions: Sequence[int] | None = None,
) -> StepReport:
    """Rung b: every vehicle after one step, each action (default: all) from each world."""
    actions = range(tensor_env.action_spec.space.n) if actions is None else actions
    report = StepReport()
    hw = tensor_env.bridge.env
    n = states.shape[0]
    imported = tensor_env.state_from_highway(states)
    for action in actions:
        tensor_env.reset(
            TensorDict(state=imported, batch_size=tensor_env.batch_size), set_state=True
        )
        tensor_env.step(
            TensorDict(action=torch.full((n,), action), batch_size=tensor_env.batch_size)
        )
        mine = world_from_tensordict(tensor_env.get_state())
        after = []
        for i in range(n):
            hw.set_state(states[i])
            hw.step(TensorDict(action=torch.tensor(action)))
            after.append(hw.get_state())
        ref = world_from_tensordict(tensor_env.state_from_highway(torch.stack(after)))
        before = world_from_tensordict(imported)
        diff = _differences(mine, ref)
        bad = torch.zeros(n, dtype=torch.bool)
        for name, d in diff.items():
            report.max_error[name] = max(report.max_error[name], float(d.max()))
            bad |= (d > tolerance).any(-1)
        report.pairs += n
        report.agree += int((~bad).sum())
        for i in bad.nonzero().flatten().tolist():
            name = next(k for k in diff if (diff[k][i] > tolerance).any())
            vehicle = int((diff[name][i] > tolerance).nonzero()[0])
            err = float(diff[name][i, vehicle])
            why = _explain(before, ref, mine, i, vehicle, name)
            report.misses.append(StepMiss(i, action, vehicle, name, err, why))
    return report


def whole_episodes(
    tensor_env,
    states: TensorDictBase,
    policy: Policy,
    tolerance: float = 1e-6,
    max_steps: int = 100,
) -> torch.Tensor:
    """Rung c: from each world, the policy's actions (chosen on highway-env) replayed on both.

    Returns:
        ``[W]`` agreement horizons: the number of steps both agree to ``tolerance`` on
        every vehicle, or ``-1`` for a world that agrees until its episode ends.
    """
    n = states.shape[0]
    hw = tensor_env.bridge.env
    actions = torch.full((n, max_steps), -1, dtype=torch.int64)
    trajectories = []
    for i in range(n):
        td = hw.set_state(states[i])
        visited = []
        for t in range(max_steps):
            if (
                bool(td.get("done", torch.zeros(1, dtype=torch.bool)))
                or hw.gym_env.unwrapped.vehicle.crashed
            ):
                break
            td = policy(td.exclude("state"))
            actions[i, t] = int(td["action"])
            td = hw.step(td).get("next")
            visited.append(hw.get_state())
        trajectories.append(visited)
    horizon = torch.full((n,), -1, dtype=torch.int64)
    tensor_env.reset(
        TensorDict(state=tensor_env.state_from_highway(states), batch_size=tensor_env.batch_size),
        set_state=True,
    )
    for t in range(max_steps):
        live = actions[:, t] >= 0
        if not bool(live.any()):
            break
        tensor_env.step(
            TensorDict(action=actions[:, t].clamp(min=0), batch_size=tensor_env.batch_size)
        )
        mine = world_from_tensordict(tensor_env.get_state())
        rows = live.nonzero().flatten().tolist()
        ref = world_from_tensordict(
            tensor_env.state_from_highway(torch.stack([trajectories[i][t] for i in rows]))
        )
        mine_rows = type(mine)(
            type(mine.vehicles)(*(f[rows] for f in mine.vehicles)),
            *(None if f is None else f[rows] for f in mine[1:]),
        )
        diff = _differences(mine_rows, ref)
        bad = torch.zeros(len(rows), dtype=torch.bool)
        for d in diff.values():
            bad |= (d > tolerance).any(-1)
        for j, i in enumerate(rows):
            if bad[j] and horizon[i] < 0:
                horizon[i] = t
        actions[torch.tensor(rows)[bad], t + 1 :] = -1  # stop comparing a world that diverged
    return horizon
