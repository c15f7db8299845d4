"""Hand-written policies for highway-env's DiscreteMetaAction on Kinematics observations.

Every policy is a :class:`~tensordict.nn.TensorDictModule` reading ``"observation"``
(``[*batch, V, F]``) and writing an int64 ``"action"`` (``[*batch]``), so it plugs into
``env.rollout``, collectors and group rollouts like a learned actor. The policies keep
no state between calls: their decision depends on the current observation only, which
keeps them exact under snapshot branching.

The driving policies read the scene through a :class:`KinematicsLayout`. They only see
what highway-env observes: the ``V - 1`` nearest vehicles, and (with the default
``see_behind=False``) no vehicle more than two car lengths behind, so a "clear" lane is
clear of observed vehicles only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from torchrl_grpo.modules.kinematics import VEHICLE_LENGTH, KinematicsLayout

__all__ = [
    "FASTER",
    "IDLE",
    "LANE_LEFT",
    "LANE_RIGHT",
    "META_ACTIONS",
    "SCRIPTED_POLICIES",
    "SLOWER",
    "AggressivePolicy",
    "CautiousPolicy",
    "ConservativePolicy",
    "ConstantActionPolicy",
    "LaneChangePolicy",
    "MetaAction",
    "RandomPolicy",
    "RulePolicy",
    "ScriptedPolicy",
    "make_scripted_policy",
]

# Indices of highway-env's DiscreteMetaAction.ACTIONS_ALL (envs/common/action.py).
LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = 0, 1, 2, 3, 4
MetaAction = Literal["LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER"]
META_ACTIONS: dict[str, int] = {
    "LANE_LEFT": LANE_LEFT,
    "IDLE": IDLE,
    "LANE_RIGHT": LANE_RIGHT,
    "FASTER": FASTER,
    "SLOWER": SLOWER,
}

_DRIVING_FEATURES = ("presence", "x", "y", "vx")
# Two vehicles 2 m wide overlap laterally below 2 m; the margin covers lane changes.
_PATH_HALF_WIDTH = 2.5
# Lateral speed (m/s) above which a vehicle is taken to be changing lane; lane keeping
# stays well below it, a lane change at highway speed reaches several m/s.
_LANE_CHANGE_VY = 1.0


class ScriptedPolicy(TensorDictModule):
    """A :class:`TensorDictModule` around a decision module ``observation -> action``.

    Args:
        decider: module mapping ``[*batch, V, F]`` to int64 actions ``[*batch]``.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> class AlwaysFaster(nn.Module):
        ...     def forward(self, observation):
        ...         return torch.full(observation.shape[:-2], FASTER, dtype=torch.int64)
        >>> policy = ScriptedPolicy(AlwaysFaster())
        >>> HighwayEnv("merge-v0", seed=0).rollout(3, policy)["action"].tolist()
        [3, 3, 3]
    """

    def __init__(
        self, decider: nn.Module, in_key: NestedKey = "observation", out_key: NestedKey = "action"
    ) -> None:
        super().__init__(decider, in_keys=[in_key], out_keys=[out_key])


class _Constant(nn.Module):
    def __init__(self, action: int) -> None:
        super().__init__()
        self.action = action

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.full(
            observation.shape[:-2], self.action, dtype=torch.int64, device=observation.device
        )


class ConstantActionPolicy(ScriptedPolicy):
    """Always plays the same action.

    Args:
        action: an action index or a DiscreteMetaAction name.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> policy = ConstantActionPolicy("SLOWER")
        >>> from tensordict import TensorDict
        >>> policy(TensorDict(observation=torch.zeros(2, 3, 5, 5), batch_size=[2, 3]))[
        ...     "action"].unique().tolist()
        [4]
    """

    def __init__(
        self,
        action: int | MetaAction,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        if isinstance(action, str):
            if action not in META_ACTIONS:
                raise ValueError(
                    f"Unknown action {action!r}; expected one of {list(META_ACTIONS)}."
                )
            action = META_ACTIONS[action]
        super().__init__(_Constant(int(action)), in_key, out_key)


class _Random(nn.Module):
    def __init__(self, n_actions: int, seed: int | None) -> None:
        super().__init__()
        self.n_actions = n_actions
        self.generator = torch.Generator()
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(seed)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        # Draw on the CPU generator, then move: the sequence is the same on any device.
        action = torch.randint(
            self.n_actions, observation.shape[:-2], generator=self.generator, dtype=torch.int64
        )
        return action.to(observation.device)


class RandomPolicy(ScriptedPolicy):
    """Uniformly random actions from its own seeded generator.

    Args:
        n_actions: number of discrete actions.
        seed: seed of the policy's :class:`torch.Generator`; ``None`` seeds it from
            the OS. A copy (deepcopy, pickle, e.g. one per collector worker) carries
            the generator state and so repeats the same draws: seed each copy.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict(observation=torch.zeros(8, 5, 5), batch_size=[8])
        >>> a = RandomPolicy(5, seed=0)(td.clone())["action"]
        >>> b = RandomPolicy(5, seed=0)(td.clone())["action"]
        >>> bool((a == b).all()), bool(((a >= 0) & (a < 5)).all())
        (True, True)
    """

    def __init__(
        self,
        n_actions: int = 5,
        seed: int | None = None,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        super().__init__(_Random(n_actions, seed), in_key, out_key)


@dataclass
class _Scene:
    """The decoded scene, all tensors ``[*batch]`` or ``[*batch, V - 1]``."""

    speed: torch.Tensor  # ego longitudinal speed, m/s
    lane: torch.Tensor  # ego lane index, 0 = leftmost
    lanes_count: int
    present: torch.Tensor
    dx: torch.Tensor  # centre-to-centre, m, > 0 ahead
    dy: torch.Tensor  # m, > 0 to the right
    dvx: torch.Tensor  # other minus ego, m/s
    rel_lane: torch.Tensor  # other's lane minus ego's lane
    drift: torch.Tensor  # other's lane-change direction: -1 left, 0 none, +1 right
    ego_drift: torch.Tensor  # the ego's lane-change direction

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


def _time_to_collision(gap: torch.Tensor, closing: torch.Tensor) -> torch.Tensor:
    inf = torch.full_like(gap, float("inf"))
    return torch.where(closing > 0, gap / closing.clamp_min(1e-6), inf)


def _select(
    conditions: list[tuple[torch.Tensor, int]], default: int, like: torch.Tensor
) -> torch.Tensor:
    """First matching action of an ordered rule list, elementwise over the batch."""
    action = torch.full(like.shape, default, dtype=torch.int64, device=like.device)
    for condition, value in reversed(conditions):
        action = torch.where(condition, torch.full_like(action, value), action)
    return action


class _Driver(nn.Module):
    """Decodes the table into a :class:`_Scene` and leaves the decision to ``decide``."""

    def __init__(self, layout: KinematicsLayout) -> None:
        super().__init__()
        layout.require(_DRIVING_FEATURES)
        self.layout = layout

    def scene(self, observation: torch.Tensor) -> _Scene:
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
        return _Scene(
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
        return self.decide(self.scene(observation))

    def decide(self, scene: _Scene) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError


def _layout_or_default(layout: KinematicsLayout | None) -> KinematicsLayout:
    return KinematicsLayout() if layout is None else layout


class _Rule(_Driver):
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

    def decide(self, scene: _Scene) -> torch.Tensor:
        speed = scene.speed.clamp_min(1.0)
        brake_gap = self.min_gap + self.brake_headway * speed
        free_gap = self.min_gap + self.free_headway * speed

        gap, closing = scene.leader(0)
        ttc = _time_to_collision(gap, closing)
        danger = (gap < brake_gap) | (ttc < self.brake_ttc)
        # FASTER raises the target speed by one step: judge the time to collision
        # at the speed we would reach.
        faster_ttc = _time_to_collision(gap, closing + self.speed_step)
        free = (gap > free_gap) & (faster_ttc > self.free_ttc)
        brake_ttc = torch.full_like(ttc, self.brake_ttc)

        def lane(offset: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            lane_gap, lane_closing = scene.leader(offset)
            safe = scene.safe_to_enter(offset, self.change_gap, self.change_ttc)
            return safe, lane_gap, _time_to_collision(lane_gap, lane_closing)

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


class RulePolicy(ScriptedPolicy):
    """A hand-written highway driver.

    Rules, by priority:

    1. The leader in its path is too close (gap below
       ``min_gap + brake_headway * speed``) or closing fast (time to collision below
       ``brake_ttc``): move to a safe neighbouring lane that closes in more slowly
       (right first); if a collision is imminent (gap below ``min_gap`` or time to
       collision below ``emergency_ttc``), a lane with only ``emergency_gap`` of room
       will do; otherwise brake.
    2. Move right when the right lane is safe and offers no less room (highway-env
       rewards the rightmost lane).
    3. Accelerate when the road ahead is free: gap above
       ``min_gap + free_headway * speed`` and time to collision, at the speed FASTER
       leads to, above ``free_ttc``.
    4. Move to a safe lane with strictly more room, left first (overtaking).
    5. Keep lane and speed.

    A lane is safe when every observed vehicle in it, ahead or behind, leaves
    ``change_gap`` metres plus ``change_ttc`` seconds of the speed at which it and the
    ego close in. A vehicle moving sideways (``vy`` observed) counts in both lanes, and
    rules 2 and 4 wait until the ego has finished its own lane change. highway-env's
    lowest target speed (20 m/s) is above that of some traffic, so braking alone
    cannot avoid every collision: rule 1 prefers leaving the lane.

    Args:
        layout: how the observation is laid out; defaults to highway-env's default
            Kinematics observation on 3 lanes.
        min_gap: standstill gap (m).
        brake_headway: time headway (s) below which it brakes.
        brake_ttc: time to collision (s) below which it brakes.
        free_headway: time headway (s) above which the road ahead is free.
        free_ttc: time to collision (s) above which the road ahead is free.
        change_gap: gap (m) every vehicle of a target lane must leave, ahead or
            behind.
        change_ttc: extra seconds of closing speed that gap must cover.
        speed_step: speed gained by one FASTER (m/s; 5 with highway-env's default
            target speeds 20, 25, 30).
        emergency_gap: gap (m) accepted in a target lane when a collision ahead is
            imminent (gap below ``min_gap`` or time to collision below
            ``emergency_ttc``).
        emergency_ttc: time to collision (s) of an imminent collision; also the
            closing-speed margin of an emergency lane change.
        prefer_right: apply rule 2.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from tensordict import TensorDict
        >>> policy = RulePolicy()
        >>> obs = torch.zeros(5, 5)
        >>> obs[0] = torch.tensor([1.0, 0.5, 0.0, 25 / 80, 0.0])  # ego: 25 m/s, left lane
        >>> obs[1] = torch.tensor([1.0, 10 / 200, 0.0, -5 / 80, 0.0])  # 10 m ahead, slower
        >>> obs[2] = torch.tensor([1.0, 0.0, 1 / 3, 0.0, 0.0])  # beside, in the right lane
        >>> policy(TensorDict(observation=obs))["action"].item() == SLOWER
        True
    """

    def __init__(
        self,
        layout: KinematicsLayout | None = None,
        *,
        min_gap: float = 5.0,
        brake_headway: float = 1.5,
        brake_ttc: float = 4.0,
        free_headway: float = 3.0,
        free_ttc: float = 8.0,
        change_gap: float = 3.0,
        change_ttc: float = 3.0,
        speed_step: float = 5.0,
        emergency_gap: float = 1.0,
        emergency_ttc: float = 2.0,
        prefer_right: bool = True,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        decider = _Rule(
            _layout_or_default(layout),
            min_gap=min_gap,
            brake_headway=brake_headway,
            brake_ttc=brake_ttc,
            free_headway=free_headway,
            free_ttc=free_ttc,
            change_gap=change_gap,
            change_ttc=change_ttc,
            speed_step=speed_step,
            emergency_gap=emergency_gap,
            emergency_ttc=emergency_ttc,
            prefer_right=prefer_right,
        )
        super().__init__(decider, in_key, out_key)

    @classmethod
    def from_highway_config(cls, config: dict[str, Any], **kwargs: Any) -> RulePolicy:
        """Builds the policy for a highway-env config (``env.unwrapped.config``).

        Args:
            config: the env config.
            **kwargs: forwarded to the constructor.

        Returns:
            The policy.

        Example:
            >>> RulePolicy.from_highway_config(
            ...     {"observation": {"type": "Kinematics"}, "lanes_count": 4}
            ... ).module.layout.lanes_count
            4
        """
        return cls(KinematicsLayout.from_highway_config(config), **kwargs)


class _Aggressive(_Driver):
    def __init__(self, layout: KinematicsLayout, overtake_headway: float, brake_ttc: float):
        super().__init__(layout)
        self.overtake_headway = overtake_headway
        self.brake_ttc = brake_ttc

    def decide(self, scene: _Scene) -> torch.Tensor:
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

        emergency = _time_to_collision(gap, closing) < self.brake_ttc
        return _select(
            [
                (blocked & clear(-1), LANE_LEFT),
                (blocked & clear(+1), LANE_RIGHT),
                (emergency, SLOWER),
            ],
            FASTER,
            gap,
        )


class AggressivePolicy(ScriptedPolicy):
    """Branch policy "aggressive": full speed, overtakes, brakes only at the last moment.

    Plays FASTER; when the leader is within ``overtake_headway`` seconds it squeezes
    into a neighbouring lane (left first) with a short clear window; it brakes only
    when the time to collision drops below ``brake_ttc``. It can crash: it is meant to
    give a group a risky member.

    Args:
        layout: observation layout (highway-env's default if ``None``).
        overtake_headway: time headway (s) at which it starts overtaking.
        brake_ttc: time to collision (s) below which it brakes.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from tensordict import TensorDict
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(2, 5) for f in layout.features}  # two scenes
        >>> cols["presence"][:, :2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][:, 0], cols["vx"][:, 0] = 4.0, 25.0  # ego: middle lane, 25 m/s
        >>> cols["x"][:, 1] = torch.tensor([100.0, 12.0])  # the other: 100 m / 12 m ahead
        >>> obs = layout.encode(cols)
        >>> AggressivePolicy(layout)(TensorDict(observation=obs, batch_size=[2]))[
        ...     "action"].tolist()  # FASTER when the lane is free, else LANE_LEFT
        [3, 0]
    """

    def __init__(
        self,
        layout: KinematicsLayout | None = None,
        *,
        overtake_headway: float = 1.5,
        brake_ttc: float = 1.5,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        decider = _Aggressive(_layout_or_default(layout), overtake_headway, brake_ttc)
        super().__init__(decider, in_key, out_key)


class _KeepDistance(_Driver):
    """Keeps lane; brakes when the leader is within a headway or closing fast."""

    def __init__(self, layout: KinematicsLayout, headway: float, ttc: float) -> None:
        super().__init__(layout)
        self.headway = headway
        self.ttc = ttc

    def too_close(self, scene: _Scene) -> torch.Tensor:
        gap, closing = scene.leader(0)
        speed = scene.speed.clamp_min(1.0)
        return (gap < VEHICLE_LENGTH + self.headway * speed) | (
            _time_to_collision(gap, closing) < self.ttc
        )

    def decide(self, scene: _Scene) -> torch.Tensor:
        return _select([(self.too_close(scene), SLOWER)], IDLE, scene.speed)


class ConservativePolicy(ScriptedPolicy):
    """Branch policy "conservative": keeps lane and a long distance to the leader.

    Plays SLOWER while the leader is within ``headway`` seconds or closer than
    ``ttc`` seconds to collision, IDLE otherwise; never changes lane.

    Args:
        layout: observation layout (highway-env's default if ``None``).
        headway: time headway (s) it keeps.
        ttc: time to collision (s) below which it brakes.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from tensordict import TensorDict
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(2, 5) for f in layout.features}  # two scenes
        >>> cols["presence"][:, :2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][:, 0], cols["vx"][:, 0] = 4.0, 25.0  # ego: middle lane, 25 m/s
        >>> cols["x"][:, 1] = torch.tensor([100.0, 60.0])  # the other: 100 m / 60 m ahead
        >>> obs = layout.encode(cols)
        >>> ConservativePolicy(layout)(TensorDict(observation=obs, batch_size=[2]))[
        ...     "action"].tolist()  # IDLE beyond a 3 s headway, SLOWER within it
        [1, 4]
    """

    def __init__(
        self,
        layout: KinematicsLayout | None = None,
        *,
        headway: float = 3.0,
        ttc: float = 10.0,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        decider = _KeepDistance(_layout_or_default(layout), headway, ttc)
        super().__init__(decider, in_key, out_key)


class _LaneChange(_KeepDistance):
    def __init__(self, layout: KinematicsLayout, offset: int, headway: float, ttc: float) -> None:
        super().__init__(layout, headway, ttc)
        self.offset = offset

    def decide(self, scene: _Scene) -> torch.Tensor:
        speed = scene.speed.clamp_min(1.0)
        front = VEHICLE_LENGTH + 0.5 * speed
        can_move = scene.lane_exists(self.offset) & ~scene.occupied(
            self.offset, 2 * VEHICLE_LENGTH, front
        )
        move = LANE_LEFT if self.offset < 0 else LANE_RIGHT
        return _select([(can_move, move), (self.too_close(scene), SLOWER)], IDLE, scene.speed)


class LaneChangePolicy(ScriptedPolicy):
    """Branch policies "left" and "right": change lane that way, then keep lane.

    Plays LANE_LEFT (or LANE_RIGHT) whenever that lane exists and is clear beside the
    ego, so it ends in the outermost lane on that side; otherwise keeps lane, braking
    when the leader is within ``headway`` seconds. Being stateless, it cannot tell
    "one lane change" from "keep going that way".

    Args:
        direction: ``"left"`` or ``"right"``.
        layout: observation layout (highway-env's default if ``None``).
        headway: time headway (s) kept while in lane.
        ttc: time to collision (s) below which it brakes.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from tensordict import TensorDict
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(2, 5) for f in layout.features}  # two scenes
        >>> cols["presence"][:, 0] = 1.0  # the ego alone on the road
        >>> cols["y"][:, 0] = torch.tensor([4.0, 0.0])  # in the middle / leftmost lane
        >>> cols["vx"][:, 0] = 25.0
        >>> td = TensorDict(observation=layout.encode(cols), batch_size=[2])
        >>> LaneChangePolicy("left", layout)(td)["action"].tolist()  # LANE_LEFT, then IDLE
        [0, 1]
        >>> LaneChangePolicy("right", layout)(td)["action"].tolist()  # LANE_RIGHT
        [2, 2]
    """

    def __init__(
        self,
        direction: Literal["left", "right"],
        layout: KinematicsLayout | None = None,
        *,
        headway: float = 1.5,
        ttc: float = 5.0,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        if direction not in ("left", "right"):
            raise ValueError(f"direction must be 'left' or 'right', got {direction!r}.")
        offset = -1 if direction == "left" else 1
        decider = _LaneChange(_layout_or_default(layout), offset, headway, ttc)
        super().__init__(decider, in_key, out_key)


class _Cautious(_Driver):
    def __init__(self, layout: KinematicsLayout, near_distance: float) -> None:
        super().__init__(layout)
        self.near_distance = near_distance

    def decide(self, scene: _Scene) -> torch.Tensor:
        near = scene.nearest_distance() < self.near_distance
        return _select([(near, SLOWER)], IDLE, scene.speed)


class CautiousPolicy(ScriptedPolicy):
    """Branch policy "cautious": keeps lane and speed, slows when anything is near.

    Plays SLOWER whenever an observed vehicle ahead of or beside the ego is within
    ``near_distance`` metres (any lane), IDLE otherwise.

    Args:
        layout: observation layout (highway-env's default if ``None``).
        near_distance: radius (m) that triggers braking.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from tensordict import TensorDict
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(2, 5) for f in layout.features}  # two scenes
        >>> cols["presence"][:, :2] = 1.0  # the ego (row 0) and one other vehicle
        >>> cols["y"][:, 0], cols["vx"][:, 0] = 4.0, 25.0  # ego: middle lane, 25 m/s
        >>> cols["x"][:, 1] = torch.tensor([-20.0, 15.0])  # the other: 20 m behind / 15 m ahead
        >>> cols["y"][:, 1] = 4.0  # ... in the right lane
        >>> obs = layout.encode(cols)
        >>> CautiousPolicy(layout)(TensorDict(observation=obs, batch_size=[2]))[
        ...     "action"].tolist()  # IDLE, SLOWER for a vehicle near ahead (any lane)
        [1, 4]
    """

    def __init__(
        self,
        layout: KinematicsLayout | None = None,
        *,
        near_distance: float = 30.0,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        super().__init__(_Cautious(_layout_or_default(layout), near_distance), in_key, out_key)


def _idle(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return ConstantActionPolicy(IDLE, **kwargs)


def _slower(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return ConstantActionPolicy(SLOWER, **kwargs)


def _random(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return RandomPolicy(**kwargs)


def _left(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return LaneChangePolicy("left", layout, **kwargs)


def _right(layout: KinematicsLayout | None = None, **kwargs: Any) -> ScriptedPolicy:
    return LaneChangePolicy("right", layout, **kwargs)


#: Scripted policies by name. Each entry is called as ``factory(layout, **kwargs)``.
#: "aggressive", "conservative", "left", "right" and "cautious" are the five branch
#: policies of the original CARLA prototype demo.
SCRIPTED_POLICIES: dict[str, Callable[..., ScriptedPolicy]] = {
    "idle": _idle,
    "slower": _slower,
    "random": _random,
    "rule": RulePolicy,
    "aggressive": AggressivePolicy,
    "conservative": ConservativePolicy,
    "left": _left,
    "right": _right,
    "cautious": CautiousPolicy,
}


def make_scripted_policy(
    name: str, layout: KinematicsLayout | None = None, **kwargs: Any
) -> ScriptedPolicy:
    """Builds a scripted policy from :data:`SCRIPTED_POLICIES` by name.

    Args:
        name: a key of :data:`SCRIPTED_POLICIES`.
        layout: observation layout, for the policies that read the scene.
        **kwargs: forwarded to the policy's constructor.

    Returns:
        The policy.

    Example:
        >>> from tensordict import TensorDict
        >>> policy = make_scripted_policy("random", seed=0)
        >>> policy(TensorDict(observation=torch.zeros(3, 5, 5), batch_size=[3]))[
        ...     "action"].shape
        torch.Size([3])
    """
    try:
        factory = SCRIPTED_POLICIES[name]
    except KeyError:
        raise KeyError(
            f"Unknown scripted policy {name!r}; expected one of {sorted(SCRIPTED_POLICIES)}."
        ) from None
    return factory(layout, **kwargs)
