"""What a merge-v0 step reports: the Kinematics observation with the obstacle, the merging reward.

The observation is ``KinematicObservation.observe`` with ``order="sorted"`` and
obstacles included: the ego's row in world coordinates, then up to
``vehicles_count - 1`` rows among the vehicles and the obstacle closer than the
perception distance (``sqrt(fma(dy, dy, dx * dx))``, ``np.linalg.norm``'s value here)
and less than two lengths behind along the ego's CURRENT lane
(``lane_distance_to``), stably sorted by that distance's magnitude, relative to the
ego. The obstacle's velocity is 0. ``features_range`` is the one highway-env fixes at
the first observation after a reset.

The reward is ``MergeEnv._reward``: the weighted terms summed in ``_rewards``' order
(collision, the current lane's id, the scaled speed, a lane-change action, the sum
over the vehicles on the merge lane of ``(target_speed - speed) / target_speed``, in
road order), mapped by ``lmap`` from ``[collision + merging, high_speed +
right_lane]`` to ``[0, 1]``, unclipped.

Example:
    >>> import torch
    >>> from torchrl_grpo.envs import tensor_params
    >>> from torchrl_grpo.sim.merge_reset import reset_merge
    >>> from torchrl_grpo.sim.state import empty_world
    >>> params = tensor_params("merge-v0")
    >>> world = empty_world(1, params.num_vehicles, torch.float64)
    >>> draws = torch.tensor([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]], dtype=torch.float64)
    >>> world = reset_merge(world, torch.ones(1, dtype=torch.bool), draws, params)
    >>> out = observe_merge(world, params, torch.tensor([1]))
    >>> [round(v, 4) for v in out["observation"][0, 0].tolist()]  # the ego at (30, 4), 30 m/s
    [1.0, 0.15, 0.5, 0.375, 0.0]
    >>> round(float(out["reward"][0]), 4)  # (0.1 * 1 + 0.2 * 1 + 1.5) / 1.8
    1.0
"""

from __future__ import annotations

import torch

from torchrl_grpo.sim import lanes as L
from torchrl_grpo.sim.merge_params import MergeParams
from torchrl_grpo.sim.observation import kinematics_table

__all__ = ["MERGE_REWARD_COMPONENTS", "ego_on_road", "merge_reward", "observe_merge", "outputs"]

#: ``MergeEnv._rewards``' keys, in its order.
MERGE_REWARD_COMPONENTS = (
    "collision_reward",
    "right_lane_reward",
    "high_speed_reward",
    "lane_change_reward",
    "merging_speed_reward",
)


def _observation(v, params: MergeParams, intentions=None) -> torch.Tensor:
    obs = params.observation
    lane = v.lane[:, :1]
    s = L.local_coordinates(v.x, v.y, lane, params.road.lanes)[0]
    along = s - s[:, :1]
    dx, dy = v.x - v.x[:, :1], v.y - v.y[:, :1]
    visible = v.present & (torch.sqrt(torch.addcmul(dx * dx, dy, dy)) < obs.perception_distance)
    visible[:, 0] = False
    behind_ok = -2 * params.vehicle.length < along
    if obs.see_behind:  # obstacles are always held to the two-length rule
        behind_ok[:, : params.obstacle_row] = True
    visible = visible & behind_ok
    key = torch.where(visible, along.abs(), torch.full_like(along, float("inf")))
    order = torch.argsort(key, dim=-1, stable=True)[:, : obs.vehicles_count - 1]
    shown = visible.gather(1, order)
    return kinematics_table(v, params, order, shown, intentions)


def ego_on_road(v, params) -> torch.Tensor:
    """``[B]``: the ego's ``on_road`` (within its current lane's width and ends).

    Example:
        >>> # see the module's example
    """
    lane = v.lane[:, 0]
    s, r = L.local_coordinates(v.x[:, 0], v.y[:, 0], lane, params.road.lanes)
    return L.on_lane(s, r, lane, params.road.lanes)


def outputs(
    v, params, reward, parts, terminated, truncated, on_road, intentions=None
) -> dict[str, torch.Tensor]:
    """A step's report on a lane graph (merge, roundabout, intersection): ``observe_world``'s keys.

    ``intentions`` are the routed worlds' ``route_intentions`` (``None``: no routes).

    Example:
        >>> # see the module's example
    """
    return {
        "observation": _observation(v, params, intentions),
        "reward": reward,
        "terminated": terminated,
        "truncated": truncated,
        "crashed": v.crashed[:, 0],
        "on_road": on_road,
        "speed": v.speed[:, 0],
        "ego_position": torch.stack([v.x[:, 0], v.y[:, 0]], dim=-1),
        "ego_heading": v.heading[:, 0],
        "reward_components": parts,
    }


def merge_reward(
    v, params: MergeParams, action: torch.Tensor | None
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """``(reward, components)`` of B merge worlds after ``action`` (``None``: no action yet).

    Example:
        >>> # see the module's example
    """
    r = params.reward
    speed = v.speed[:, 0]
    lane_id = torch.tensor(params.road.lane_id, device=speed.device)[v.lane[:, 0]]
    lo, hi = r.reward_speed_range
    merging = torch.zeros_like(speed)
    for k in range(params.obstacle_row):  # road.vehicles, in order (the obstacle is no vehicle)
        on_merge = v.lane[:, k] == r.merge_lane
        deficit = (v.target_speed[:, k] - v.speed[:, k]) / v.target_speed[:, k]
        merging = torch.where(on_merge, merging + deficit, merging)
    if action is None:
        changed = torch.zeros_like(v.crashed[:, 0])
    else:
        changed = (action == 0) | (action == 2)
    parts = {
        "collision_reward": v.crashed[:, 0].to(speed.dtype),
        "right_lane_reward": (lane_id / 1).to(speed.dtype),
        "high_speed_reward": 0 + (speed - lo) * (1 - 0) / (hi - lo),
        "lane_change_reward": changed.to(speed.dtype),
        "merging_speed_reward": merging,
    }
    total = torch.zeros_like(speed)
    for name in MERGE_REWARD_COMPONENTS:
        total = total + getattr(r, name) * parts[name]
    low = r.collision_reward + r.merging_speed_reward
    high = r.high_speed_reward + r.right_lane_reward
    return 0 + (total - low) * (1 - 0) / (high - low), parts


def observe_merge(
    world, params: MergeParams, action: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    """What an env step reports of B merge worlds (the keys of ``observe_world``).

    Args:
        world: B merge worlds.
        params: the constants.
        action: the step's ``[B]`` actions (the lane-change term), ``None`` at reset.

    Returns:
        ``observation``, ``reward``, ``terminated``, ``truncated``, ``crashed``,
        ``on_road``, ``speed``, ``ego_position``, ``ego_heading``, ``reward_components``.

    Example:
        >>> # see the module's example
    """
    v = world.vehicles
    total, parts = merge_reward(v, params, action)
    crashed = v.crashed[:, 0]
    terminated = crashed | (v.x[:, 0] > params.reward.terminal_x)
    truncated = torch.zeros_like(crashed)
    return outputs(v, params, total, parts, terminated, truncated, ego_on_road(v, params))
