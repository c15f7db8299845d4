"""The scene a driver sees, decoded from a Kinematics table, and the driver base class.

:meth:`Driver.scene` decodes the observation through a :class:`KinematicsLayout` into a
:class:`Scene`: the ego's speed and lane, and every other observed vehicle's gap,
lateral offset, relative speed and lane. A driver subclasses :class:`Driver` and maps
that scene to actions in :meth:`Driver.decide`; the drivers of the library are in
:mod:`~torchrl_grpo.modules.scripted.drivers`, and
:class:`~torchrl_grpo.modules.scene_features.SceneFeatures` reads the same scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from torchrl_grpo.modules.kinematics_table import VEHICLE_LENGTH, KinematicsLayout

__all__ = ["Driver", "Scene", "time_to_collision"]

_DRIVING_FEATURES = ("presence", "x", "y", "vx")
# Two vehicles 2 m wide overlap laterally below 2 m; the margin covers lane changes.
_PATH_HALF_WIDTH = 2.5
# Lateral speed (m/s) above which a vehicle is taken to be changing lane; lane keeping
# stays well below it, a lane change at highway speed reaches several m/s.
_LANE_CHANGE_VY = 1.0


@dataclass
class Scene:
    """The decoded scene, all tensors ``[*batch]`` or ``[*batch, V - 1]``.

    Built by :meth:`Driver.scene`. The per-vehicle tensors hold the ``V - 1`` other
    rows of the observation, absent ones included (see ``present``).

    Attributes:
        speed: ego longitudinal speed, m/s.
        lane: ego lane index, 0 = leftmost.
        lanes_count: number of lanes of the road.
        present: whether each other row holds a vehicle.
        dx: centre-to-centre longitudinal distance, m, > 0 ahead.
        dy: lateral distance, m, > 0 to the right.
        dvx: longitudinal speed, other minus ego, m/s.
        rel_lane: the other's lane minus the ego's lane.
        drift: the other's lane-change direction: -1 left, 0 none, +1 right.
        ego_drift: the ego's lane-change direction.

    Example:
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:2] = 1.0
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego, middle lane, 25 m/s
        >>> cols["x"][1], cols["vx"][1] = 25.0, -5.0  # 25 m ahead, 5 m/s slower
        >>> scene = Driver(layout).scene(layout.encode(cols))
        >>> scene.lane.item(), [round(v.item(), 2) for v in scene.leader(0)]
        (1, [20.0, 5.0])
    """

    speed: torch.Tensor
    lane: torch.Tensor
    lanes_count: int
    present: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    dvx: torch.Tensor
    rel_lane: torch.Tensor
    drift: torch.Tensor
    ego_drift: torch.Tensor

    def lane_mask(self, offset: int) -> torch.Tensor:
        """Present vehicles in the lane at ``offset`` (0: own path, -1 left, +1 right).

        A vehicle changing lane counts in both its lane and the one it moves to.
        """
        in_lane = (self.rel_lane == offset) | (
            self.drift.ne(0) & (self.rel_lane + self.drift == offset)
        )
        if offset == 0:
            # Anything overlapping laterally is in the way, whatever lane it is
            # assigned to, so cars cutting in and our own lane changes are covered.
            in_lane = in_lane | (self.dy.abs() < _PATH_HALF_WIDTH)
        return self.present & in_lane

    def lane_exists(self, offset: int) -> torch.Tensor:
        """Whether the lane at ``offset`` exists."""
        target = self.lane + offset
        return (target >= 0) & (target < self.lanes_count)

    def leader(self, offset: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Gap and closing speed to the nearest vehicle ahead in the lane at ``offset``.

        The gap is bumper to bumper (m, inf if none); the closing speed is > 0 when
        the ego is catching up (m/s).
        """
        ahead = self.lane_mask(offset) & (self.dx > 0)
        if ahead.shape[-1] == 0:
            inf = torch.full_like(self.speed, float("inf"))
            return inf, torch.zeros_like(self.speed)
        dist = torch.where(ahead, self.dx, torch.full_like(self.dx, float("inf")))
        nearest, idx = dist.min(-1)
        closing = -self.dvx.gather(-1, idx.unsqueeze(-1)).squeeze(-1)
        closing = torch.where(torch.isfinite(nearest), closing, torch.zeros_like(closing))
        return (nearest - VEHICLE_LENGTH).clamp_min(0.0), closing

    def safe_to_enter(self, offset: int, min_gap: float, ttc: float) -> torch.Tensor:
        """Whether the lane at ``offset`` exists and has room for the ego.

        Every observed vehicle of that lane must be at least ``min_gap`` metres
        (bumper to bumper) away, plus ``ttc`` seconds of the speed at which it and the
        ego close in: a leader slower than the ego, or a follower faster than it.
        """
        ahead = self.dx >= 0
        gap = self.dx.abs() - VEHICLE_LENGTH
        closing = torch.where(ahead, -self.dvx, self.dvx).clamp_min(0.0)
        unsafe = self.lane_mask(offset) & (gap < min_gap + ttc * closing)
        return self.lane_exists(offset) & ~unsafe.any(-1)

    def occupied(self, offset: int, back: float, front: torch.Tensor) -> torch.Tensor:
        """Whether a vehicle of the lane at ``offset`` is within ``[-back, front]`` m."""
        near = self.lane_mask(offset) & (self.dx > -back) & (self.dx < front.unsqueeze(-1))
        return near.any(-1)

    def nearest_distance(self) -> torch.Tensor:
        """Distance (m) to the nearest present vehicle not behind the ego."""
        dist = torch.hypot(self.dx, self.dy)
        relevant = self.present & (self.dx > -VEHICLE_LENGTH)
        dist = torch.where(relevant, dist, torch.full_like(dist, float("inf")))
        if dist.shape[-1] == 0:
            return torch.full_like(self.speed, float("inf"))
        return dist.min(-1).values


def time_to_collision(gap: torch.Tensor, closing: torch.Tensor) -> torch.Tensor:
    """Seconds until a gap of ``gap`` m closes at ``closing`` m/s (inf if not closing).

    Example:
        >>> time_to_collision(torch.tensor([20.0, 20.0]), torch.tensor([5.0, -1.0])).tolist()
        [4.0, inf]
    """
    inf = torch.full_like(gap, float("inf"))
    return torch.where(closing > 0, gap / closing.clamp_min(1e-6), inf)


class Driver(nn.Module):
    """Decodes the table into a :class:`Scene` and leaves the decision to :meth:`decide`.

    Subclasses implement :meth:`decide`; wrapped in a
    :class:`~torchrl_grpo.modules.ScriptedPolicy`, a driver is a policy.

    Args:
        layout: how the observation is laid out (needs presence, x, y and vx).

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.modules import ScriptedPolicy
        >>> from torchrl_grpo.modules.scripted.actions import SLOWER
        >>> class BrakeWhenFollowing(Driver):
        ...     def decide(self, scene):
        ...         gap, _ = scene.leader(0)
        ...         return torch.where(gap < 30.0, SLOWER, 1)  # else IDLE
        >>> layout = KinematicsLayout()
        >>> cols = {f: torch.zeros(2, 5) for f in layout.features}  # two scenes
        >>> cols["presence"][:, :2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][:, 0], cols["vx"][:, 0] = 4.0, 25.0  # ego: middle lane, 25 m/s
        >>> cols["x"][:, 1] = torch.tensor([100.0, 20.0])  # the other: 100 m / 20 m ahead
        >>> policy = ScriptedPolicy(BrakeWhenFollowing(layout))
        >>> policy(TensorDict(observation=layout.encode(cols), batch_size=[2]))[
        ...     "action"].tolist()
        [1, 4]
    """

    def __init__(self, layout: KinematicsLayout) -> None:
        super().__init__()
        layout.require(_DRIVING_FEATURES)
        self.layout = layout

    def scene(self, observation: torch.Tensor) -> Scene:
        """Decodes ``[*batch, V, F]`` observations into a :class:`Scene`."""
        cols = self.layout.decode(observation.float())
        presence = cols["presence"]
        lane_width = self.layout.lane_width
        ego_y = cols["y"][..., 0]
        lane = torch.round(ego_y / lane_width).clamp(0, self.layout.lanes_count - 1)
        other_lane = torch.round((ego_y.unsqueeze(-1) + cols["y"][..., 1:]) / lane_width)
        if "vy" in cols:
            ego_vy = cols["vy"][..., :1]
            # Rows 1+ are relative to the ego: add its lateral speed back.
            vy = torch.cat([ego_vy, cols["vy"][..., 1:] + ego_vy], dim=-1)
        else:
            vy = torch.zeros_like(cols["x"])
        drift = torch.where(vy.abs() > _LANE_CHANGE_VY, vy.sign(), torch.zeros_like(vy)).long()
        return Scene(
            speed=cols["vx"][..., 0],
            lane=lane.long(),
            lanes_count=self.layout.lanes_count,
            present=presence[..., 1:] > 0.5,
            dx=cols["x"][..., 1:],
            dy=cols["y"][..., 1:],
            dvx=cols["vx"][..., 1:],
            rel_lane=(other_lane - lane.unsqueeze(-1)).long(),
            drift=drift[..., 1:],
            ego_drift=drift[..., 0],
        )

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` observations to int64 actions ``[*batch]``."""
        return self.decide(self.scene(observation))

    def decide(self, scene: Scene) -> torch.Tensor:  # pragma: no cover - abstract
        """The actions, int64 ``[*batch]``, for ``scene`` (implemented by subclasses)."""
        raise NotImplementedError
