"""A policy network over driving features of the scene instead of the raw table.

highway-env's Kinematics table holds positions and speeds normalised by 200 m and
80 m/s, the ego row in absolute coordinates, the other vehicles in an order that
changes with distance. What decides a crash (the gap to the car ahead in a lane, how
fast it closes, whether a neighbouring lane has room) is a small, nonlinear function of
a few of its entries, and an MLP over the table learns it slowly: cloned from 5,000
states of the rule policy it matches 85% of the actions of held-out states, where the
same MLP over :class:`SceneFeatures` matches 95% and drives as the rule policy does
(``benchmarks/lab/bench_features.py``, docs/results.md). :class:`SceneFeatures` decodes the
table with the scene reader of the scripted drivers (:class:`~torchrl_grpo.modules.Driver`)
into 18 numbers per observation; :class:`SceneMLP` is an MLP over them.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn
from torchrl.modules import MLP

from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.modules.scripted.scene import Driver, time_to_collision

__all__ = ["FeatureMLP", "SceneFeatures", "SceneMLP"]

#: highway-env's default target speeds (DiscreteMetaAction), m/s.
DEFAULT_TARGET_SPEEDS = (20.0, 25.0, 30.0)
# Gaps beyond this many metres (or no leader at all) read as this far.
_FAR = 100.0
# The room a lane change needs, as the rule policy judges it (RulePolicy's defaults).
_CHANGE_GAP, _CHANGE_TTC = 3.0, 3.0
# A neighbouring lane counts as occupied with a vehicle within this many metres.
_NEAR = 25.0


class SceneFeatures(Driver):
    """Driving features of a Kinematics observation: ``[*batch, V, F] -> [*batch, 18]``.

    In order: the ego speed, centred on the middle of the env's target speeds and
    scaled by half their range (``(v - 25) / 5`` for highway-env's default 20, 25 and
    30 m/s), the ego's lane-change direction (-1,
    0, +1); then for the left lane, the ego's lane and the right lane: whether it
    exists, the bumper-to-bumper gap to the nearest vehicle ahead in it (m / 50, at most
    2), the speed at which the ego closes on it (m/s / 10), the inverse time to
    collision (1/s, 0 if not closing, at most 5); and for the two neighbouring lanes
    only, whether a lane change into it is safe (every vehicle of the lane leaves 3 m
    plus 3 s of closing speed) and whether a vehicle of it is within 25 m.

    Args:
        layout: how the observation is laid out (needs presence, x, y and vx).
        target_speeds: the env's ``DiscreteMetaAction`` target speeds (m/s).

    Example:
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:2] = 1.0
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego, middle lane, 25 m/s
        >>> cols["x"][1], cols["vx"][1] = 25.0, -5.0  # 25 m ahead, 5 m/s slower
        >>> features = SceneFeatures(layout)(layout.encode(cols))
        >>> [round(v, 2) for v in features[8:12].tolist()]  # the ego's lane
        [1.0, 0.4, 0.5, 0.25]
    """

    n_features = 18

    def __init__(
        self, layout: KinematicsLayout, target_speeds: Sequence[float] = DEFAULT_TARGET_SPEEDS
    ) -> None:
        super().__init__(layout)
        low, high = float(min(target_speeds)), float(max(target_speeds))
        self.speed_centre = (low + high) / 2
        # One target speed: the default's half range, 5 m/s.
        self.speed_scale = (high - low) / 2 if high > low else 5.0

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` to ``[*batch, 18]``."""
        scene = self.scene(observation)
        speed = (scene.speed - self.speed_centre) / self.speed_scale
        features = [speed, scene.ego_drift.float()]
        for offset in (-1, 0, 1):
            gap, closing = scene.leader(offset)
            ttc = time_to_collision(gap, closing)
            inverse_ttc = torch.where(
                torch.isfinite(ttc), 1.0 / ttc.clamp(min=0.1), torch.zeros_like(ttc)
            )
            far = torch.full_like(gap, _FAR)
            features += [
                scene.lane_exists(offset).float(),
                torch.where(torch.isfinite(gap), gap, far).clamp(max=_FAR) / 50.0,
                closing / 10.0,
                inverse_ttc.clamp(max=5.0),
            ]
            if offset != 0:
                near = torch.full_like(scene.speed, _NEAR)
                features += [
                    scene.safe_to_enter(offset, _CHANGE_GAP, _CHANGE_TTC).float(),
                    scene.occupied(offset, _NEAR, near).float(),
                ]
        return torch.stack(features, -1)


class FeatureMLP(nn.Module):
    """An MLP over driving features: :class:`SceneFeatures` or a subclass of it.

    Subclasses name the features in ``features_class`` (built from the layout and the
    target speeds; its class attribute ``n_features`` is the MLP's input size).
    """

    features_class: type[SceneFeatures]

    def __init__(
        self,
        layout: KinematicsLayout,
        out_features: int,
        num_cells: Sequence[int] = (256, 256),
        activation_class: type[nn.Module] = nn.Tanh,
        target_speeds: Sequence[float] = DEFAULT_TARGET_SPEEDS,
    ) -> None:
        super().__init__()
        self.features = self.features_class(layout, target_speeds)
        self.mlp = MLP(
            in_features=self.features_class.n_features,
            out_features=out_features,
            num_cells=list(num_cells),
            activation_class=activation_class,
        )

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` to ``[*batch, out_features]``."""
        return self.mlp(self.features(observation))


class SceneMLP(FeatureMLP):
    """An MLP over :class:`SceneFeatures`.

    Args:
        layout: how the observation is laid out.
        out_features: size of the output (actions for logits, 1 for a value).
        num_cells: widths of the hidden layers.
        activation_class: activation between hidden layers.
        target_speeds: the env's target speeds (see :class:`SceneFeatures`).

    Example:
        >>> net = SceneMLP(KinematicsLayout(), out_features=5, num_cells=(32,))
        >>> net(torch.zeros(4, 2, 5, 5)).shape
        torch.Size([4, 2, 5])
    """

    features_class = SceneFeatures
