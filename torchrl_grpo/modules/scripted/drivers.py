"""The scripted drivers: decisions of the driving policies, read from a :class:`Scene`.

Each driver is a :class:`~torchrl_grpo.modules.scripted.scene.Driver` (an
``nn.Module`` mapping ``[*batch, V, F]`` observations to int64 actions ``[*batch]``)
whose :meth:`~torchrl_grpo.modules.scripted.scene.Driver.decide` applies an ordered rule
list to the scene. The policies that wrap them, and document their rules and
parameters, are in :mod:`~torchrl_grpo.modules.scripted.policies`.
"""

from __future__ import annotations

import torch

from torchrl_grpo.modules.kinematics_table import VEHICLE_LENGTH, KinematicsLayout
from torchrl_grpo.modules.scripted.actions import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, SLOWER
from torchrl_grpo.modules.scripted.scene import Driver, Scene, time_to_collision

__all__ = [
    "AggressiveDriver",
    "CautiousDriver",
    "KeepDistanceDriver",
    "LaneChangeDriver",
    "RuleDriver",
]


def _select(
    conditions: list[tuple[torch.Tensor, int]], default: int, like: torch.Tensor
) -> torch.Tensor:
    """First matching action of an ordered rule list, elementwise over the batch."""
    action = torch.full(like.shape, default, dtype=torch.int64, device=like.device)
    for condition, value in reversed(conditions):
        action = torch.where(condition, torch.full_like(action, value), action)
    return action


class RuleDriver(Driver):
    """The decision of :class:`~torchrl_grpo.modules.RulePolicy` (its rules and arguments).

    Example:
        >>> from torchrl_grpo.modules import RulePolicy
        >>> driver = RulePolicy().module  # the policy's driver, with its defaults
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego: middle lane, 25 m/s
        >>> cols["x"][1], cols["vx"][1] = 10.0, -5.0  # 10 m ahead, slower: it escapes right
        >>> isinstance(driver, RuleDriver), driver(layout.encode(cols)).item() == LANE_RIGHT
        (True, True)
    """

    def __init__(
        self,
        layout: KinematicsLayout,
        min_gap: float,
        brake_headway: float,
        brake_ttc: float,
        free_headway: float,
        free_ttc: float,
        change_gap: float,
        change_ttc: float,
        speed_step: float,
        emergency_gap: float,
        emergency_ttc: float,
        prefer_right: bool,
    ) -> None:
        super().__init__(layout)
        self.min_gap = min_gap
        self.brake_headway = brake_headway
        self.brake_ttc = brake_ttc
        self.free_headway = free_headway
        self.free_ttc = free_ttc
        self.change_gap = change_gap
        self.change_ttc = change_ttc
        self.speed_step = speed_step
        self.emergency_gap = emergency_gap
        self.emergency_ttc = emergency_ttc
        self.prefer_right = prefer_right

    def decide(self, scene: Scene) -> torch.Tensor:
        """The actions, int64 ``[*batch]``, the rules give for ``scene``."""
        speed = scene.speed.clamp_min(1.0)
        brake_gap = self.min_gap + self.brake_headway * speed
        free_gap = self.min_gap + self.free_headway * speed

        gap, closing = scene.leader(0)
        ttc = time_to_collision(gap, closing)
        danger = (gap < brake_gap) | (ttc < self.brake_ttc)
        # FASTER raises the target speed by one step: judge the time to collision
        # at the speed we would reach.
        faster_ttc = time_to_collision(gap, closing + self.speed_step)
        free = (gap > free_gap) & (faster_ttc > self.free_ttc)
        brake_ttc = torch.full_like(ttc, self.brake_ttc)

        def lane(offset: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            lane_gap, lane_closing = scene.leader(offset)
            safe = scene.safe_to_enter(offset, self.change_gap, self.change_ttc)
            return safe, lane_gap, time_to_collision(lane_gap, lane_closing)

        def escape(offset: int) -> torch.Tensor:
            # Braking cannot save us from a leader slower than the lowest target
            # speed (20 m/s), so any safe lane closing in more slowly is taken, even
            # with a nearer (but faster) leader.
            safe, _, lane_ttc = lane(offset)
            return safe & (lane_ttc > torch.maximum(ttc, brake_ttc))

        # Braking no longer helps (the leader is slower than the lowest target speed
        # or too close): squeezing into a lane with a small but open gap is the
        # lesser risk.
        emergency = (gap < self.min_gap) | (ttc < self.emergency_ttc)

        def squeeze(offset: int) -> torch.Tensor:
            _, _, lane_ttc = lane(offset)
            room = scene.safe_to_enter(offset, self.emergency_gap, self.emergency_ttc)
            return room & (lane_ttc > ttc)

        def better(offset: int) -> torch.Tensor:
            # Strictly more room and slower closing: the move can never be undone by
            # the same rule on the next step.
            safe, lane_gap, lane_ttc = lane(offset)
            return safe & (lane_gap > gap) & (lane_ttc > torch.maximum(ttc, brake_ttc))

        def no_worse(offset: int) -> torch.Tensor:
            safe, lane_gap, lane_ttc = lane(offset)
            enough_gap = lane_gap >= torch.minimum(gap, free_gap)
            enough_ttc = lane_ttc >= torch.minimum(ttc, torch.full_like(ttc, self.free_ttc))
            return safe & enough_gap & enough_ttc

        # Starting another lane change in the middle of one chains moves on stale
        # gaps; only an escape may do so.
        settled = scene.ego_drift == 0
        # highway-env rewards the rightmost lane: move right whenever it costs no room.
        keep_right = no_worse(+1) if self.prefer_right else torch.zeros_like(free)
        return _select(
            [
                (danger & escape(+1), LANE_RIGHT),
                (danger & escape(-1), LANE_LEFT),
                (emergency & squeeze(+1), LANE_RIGHT),
                (emergency & squeeze(-1), LANE_LEFT),
                (danger, SLOWER),
                (settled & keep_right, LANE_RIGHT),
                (free, FASTER),
                (settled & better(-1), LANE_LEFT),
                (settled & better(+1), LANE_RIGHT),
            ],
            IDLE,
            gap,
        )


class AggressiveDriver(Driver):
    """The decision of :class:`~torchrl_grpo.modules.scripted.policies.AggressivePolicy`.

    It takes the policy's arguments.

    Example:
        >>> driver = AggressiveDriver(KinematicsLayout(), overtake_headway=1.5, brake_ttc=1.5)
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego: middle lane, 25 m/s
        >>> cols["x"][1] = 12.0  # 12 m ahead: it overtakes on the left
        >>> driver(layout.encode(cols)).item() == LANE_LEFT
        True
    """

    def __init__(self, layout: KinematicsLayout, overtake_headway: float, brake_ttc: float):
        super().__init__(layout)
        self.overtake_headway = overtake_headway
        self.brake_ttc = brake_ttc

    def decide(self, scene: Scene) -> torch.Tensor:
        """The actions, int64 ``[*batch]``, the rules give for ``scene``."""
        speed = scene.speed.clamp_min(1.0)
        gap, closing = scene.leader(0)
        blocked = gap < VEHICLE_LENGTH + self.overtake_headway * speed
        # Squeezes into any lane with a short clear window beside the ego.
        window = torch.full_like(speed, VEHICLE_LENGTH)

        def clear(offset: int) -> torch.Tensor:
            lane_gap, _ = scene.leader(offset)
            return (
                scene.lane_exists(offset)
                & ~scene.occupied(offset, VEHICLE_LENGTH, window)
                & (lane_gap > gap)
            )

        emergency = time_to_collision(gap, closing) < self.brake_ttc
        return _select(
            [
                (blocked & clear(-1), LANE_LEFT),
                (blocked & clear(+1), LANE_RIGHT),
                (emergency, SLOWER),
            ],
            FASTER,
            gap,
        )


class KeepDistanceDriver(Driver):
    """Keeps lane; brakes when the leader is within a headway or closing fast.

    The decision of :class:`~torchrl_grpo.modules.scripted.policies.ConservativePolicy`
    (its arguments).

    Example:
        >>> driver = KeepDistanceDriver(KinematicsLayout(), headway=3.0, ttc=10.0)
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego: middle lane, 25 m/s
        >>> cols["x"][1] = 60.0  # 60 m ahead, within a 3 s headway at 25 m/s
        >>> driver(layout.encode(cols)).item() == SLOWER
        True
    """

    def __init__(self, layout: KinematicsLayout, headway: float, ttc: float) -> None:
        super().__init__(layout)
        self.headway = headway
        self.ttc = ttc

    def too_close(self, scene: Scene) -> torch.Tensor:
        """Whether the leader is within the headway, or closer than ``ttc`` s to collision."""
        gap, closing = scene.leader(0)
        speed = scene.speed.clamp_min(1.0)
        return (gap < VEHICLE_LENGTH + self.headway * speed) | (
            time_to_collision(gap, closing) < self.ttc
        )

    def decide(self, scene: Scene) -> torch.Tensor:
        """The actions, int64 ``[*batch]``, the rules give for ``scene``."""
        return _select([(self.too_close(scene), SLOWER)], IDLE, scene.speed)


class LaneChangeDriver(KeepDistanceDriver):
    """Changes lane towards ``offset`` (-1 left, +1 right) while it can, else keeps distance.

    The decision of :class:`~torchrl_grpo.modules.scripted.policies.LaneChangePolicy`
    (its arguments).

    Example:
        >>> driver = LaneChangeDriver(KinematicsLayout(), offset=1, headway=1.5, ttc=5.0)
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego: middle lane, 25 m/s
        >>> cols["x"][1], cols["y"][1] = 2.0, 4.0  # beside the ego, in the right lane
        >>> driver(layout.encode(cols)).item() == IDLE  # blocked: keeps its lane
        True
    """

    def __init__(self, layout: KinematicsLayout, offset: int, headway: float, ttc: float) -> None:
        super().__init__(layout, headway, ttc)
        self.offset = offset

    def decide(self, scene: Scene) -> torch.Tensor:
        """The actions, int64 ``[*batch]``, the rules give for ``scene``."""
        speed = scene.speed.clamp_min(1.0)
        front = VEHICLE_LENGTH + 0.5 * speed
        can_move = scene.lane_exists(self.offset) & ~scene.occupied(
            self.offset, 2 * VEHICLE_LENGTH, front
        )
        move = LANE_LEFT if self.offset < 0 else LANE_RIGHT
        return _select([(can_move, move), (self.too_close(scene), SLOWER)], IDLE, scene.speed)


class CautiousDriver(Driver):
    """The decision of :class:`~torchrl_grpo.modules.scripted.policies.CautiousPolicy`.

    It takes the policy's arguments.

    Example:
        >>> driver = CautiousDriver(KinematicsLayout(), near_distance=30.0)
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego: middle lane, 25 m/s
        >>> cols["x"][1], cols["y"][1] = 15.0, -4.0  # 15 m ahead, in the left lane
        >>> driver(layout.encode(cols)).item() == SLOWER
        True
    """

    def __init__(self, layout: KinematicsLayout, near_distance: float) -> None:
        super().__init__(layout)
        self.near_distance = near_distance

    def decide(self, scene: Scene) -> torch.Tensor:
        """The actions, int64 ``[*batch]``, the rules give for ``scene``."""
        near = scene.nearest_distance() < self.near_distance
        return _select([(near, SLOWER)], IDLE, scene.speed)
