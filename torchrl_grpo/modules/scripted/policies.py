"""The driving policies: scripted drivers that read the scene, as TensorDict modules.

Every policy is a :class:`~torchrl_grpo.modules.ScriptedPolicy` reading
``"observation"`` (``[*batch, V, F]``) and writing an int64 ``"action"``
(``[*batch]``), so it plugs into ``env.rollout``, collectors and group rollouts like a
learned actor. The policies keep no state between calls: their decision depends on the
current observation only, which keeps them exact under snapshot branching.

The policies read the scene through a :class:`KinematicsLayout`. They only see what
highway-env observes: the ``V - 1`` nearest vehicles, and (with the default
``see_behind=False``) no vehicle more than two car lengths behind, so a "clear" lane is
clear of observed vehicles only. Their decisions are the drivers of
:mod:`~torchrl_grpo.modules.scripted.drivers`.
"""

from __future__ import annotations

from typing import Any, Literal

from tensordict.utils import NestedKey

from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.modules.scripted.actions import ScriptedPolicy
from torchrl_grpo.modules.scripted.drivers import (
    AggressiveDriver,
    CautiousDriver,
    KeepDistanceDriver,
    LaneChangeDriver,
    RuleDriver,
)

__all__ = [
    "AggressivePolicy",
    "CautiousPolicy",
    "ConservativePolicy",
    "LaneChangePolicy",
    "RulePolicy",
]


def _layout_or_default(layout: KinematicsLayout | None) -> KinematicsLayout:
    return KinematicsLayout() if layout is None else layout


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
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.modules.scripted.actions import SLOWER
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
        decider = RuleDriver(
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
        >>> import torch
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
        decider = AggressiveDriver(_layout_or_default(layout), overtake_headway, brake_ttc)
        super().__init__(decider, in_key, out_key)


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
        >>> import torch
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
        decider = KeepDistanceDriver(_layout_or_default(layout), headway, ttc)
        super().__init__(decider, in_key, out_key)


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
        >>> import torch
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
        decider = LaneChangeDriver(_layout_or_default(layout), offset, headway, ttc)
        super().__init__(decider, in_key, out_key)


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
        >>> import torch
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
        super().__init__(CautiousDriver(_layout_or_default(layout), near_distance), in_key, out_key)
