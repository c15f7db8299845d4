"""A policy network over every lane's nearest neighbours, ahead and behind.

:class:`~torchrl_grpo.modules.scene_features.SceneFeatures` gives each lane its nearest vehicle
ahead
and, for a lane change, one yes-or-no judgement of room. What decides a crash is often
elsewhere: the car that closes in from behind in the lane the ego moves into, or the
car ahead of the leader that makes the leader brake. :class:`NeighbourFeatures` reads,
for the ego's lane and the lanes beside it, the two nearest vehicles ahead and the
nearest behind (gap, closing speed, inverse time to collision), and the ego's own
lateral offset and speed; :class:`NeighbourMLP` is an MLP over them. A vehicle more than
two lengths behind is in the table only with the observation's ``see_behind=True``.

``model=lab model.kind=neighbours``: :func:`build_neighbours` is registered with
:func:`~torchrl_grpo.training.model_builder.register_network_kind` when this module is
imported (``import torchrl_grpo.experimental``). No recipe uses it: measured in the lab
notes (``docs/lab/tensor_sim.md``), it crashed more than the scene features.
"""

from __future__ import annotations

from typing import Literal, get_args

import torch
from omegaconf import DictConfig
from torch import nn
from torchrl.envs import EnvBase

from torchrl_grpo.modules.kinematics_table import VEHICLE_LENGTH
from torchrl_grpo.modules.scene_features import FeatureMLP, SceneFeatures
from torchrl_grpo.modules.scripted.scene import Scene
from torchrl_grpo.training.group_schemas import MLPModelConfig
from torchrl_grpo.training.model_builder import make_feature_mlp, register_network_kind

__all__ = ["NeighbourFeatures", "NeighbourMLP", "NeighboursKind", "build_neighbours"]

#: The network kind this module registers (``model.kind``).
NeighboursKind = Literal["neighbours"]

# Gaps beyond this many metres (or no vehicle at all) read as this far.
_FAR = 100.0
# Inverse times to collision are capped at this (1/s): closer than 0.2 s is lost anyway.
_MAX_INVERSE_TTC = 5.0


def _nearest(scene: Scene, offset: int, ahead: bool, rank: int) -> tuple[torch.Tensor, ...]:
    """Gap (m, ``_FAR`` if none) and closing speed (m/s, > 0 closing) of a neighbour.

    The ``rank``-th nearest (0: nearest) vehicle ahead of (or behind) the ego in the
    lane at ``offset``; bumper-to-bumper gap, clipped to ``[0, _FAR]``.
    """
    side = scene.dx > 0 if ahead else scene.dx <= 0
    member = scene.lane_mask(offset) & side
    far = torch.full_like(scene.speed, _FAR)
    if member.shape[-1] <= rank:
        return far, torch.zeros_like(scene.speed)
    dist = torch.where(member, scene.dx.abs(), torch.full_like(scene.dx, float("inf")))
    ordered, idx = dist.sort(-1)
    nearest, i = ordered[..., rank], idx[..., rank : rank + 1]
    found = torch.isfinite(nearest)
    dvx = scene.dvx.gather(-1, i).squeeze(-1)
    # Closing: the ego catches a vehicle ahead, a vehicle behind catches the ego.
    closing = torch.where(found, -dvx if ahead else dvx, torch.zeros_like(dvx))
    gap = torch.where(found, (nearest - VEHICLE_LENGTH).clamp(0.0, _FAR), far)
    return gap, closing


def _inverse_ttc(gap: torch.Tensor, closing: torch.Tensor) -> torch.Tensor:
    inverse = closing.clamp_min(0.0) / gap.clamp_min(0.1)
    return inverse.clamp(max=_MAX_INVERSE_TTC)


class NeighbourFeatures(SceneFeatures):
    """Every nearby lane's neighbours: ``[*batch, V, F] -> [*batch, 30]``.

    In order: the ego speed (centred and scaled as in
    :class:`~torchrl_grpo.modules.scene_features.SceneFeatures`), its lateral offset from the
    centre of
    its lane (m / 2), its lane-change direction (-1, 0, +1); then for the left lane,
    the ego's lane and the right lane: whether it exists; for the nearest vehicle
    ahead, the second nearest ahead and the nearest behind, the bumper-to-bumper gap
    (m / 50, at most 2) and the closing speed (m/s / 10, > 0 when the gap shrinks);
    and the inverse time to collision with the nearest ahead and the nearest behind
    (1/s, at most 5).

    It reads the scene as :class:`~torchrl_grpo.modules.scene_features.SceneFeatures` does, and
    scales the speed as it does; the other features are its own.

    Args:
        layout: how the observation is laid out (needs presence, x, y and vx).
        target_speeds: the env's ``DiscreteMetaAction`` target speeds (m/s).

    Example:
        >>> from torchrl_grpo.modules import KinematicsLayout
        >>> layout = KinematicsLayout()  # highway-env's default observation, 3 lanes
        >>> cols = {f: torch.zeros(5) for f in layout.features}
        >>> cols["presence"][:3] = 1.0
        >>> cols["y"][0], cols["vx"][0] = 4.0, 25.0  # the ego, middle lane, 25 m/s
        >>> cols["x"][1], cols["vx"][1] = 25.0, -5.0  # 25 m ahead, 5 m/s slower
        >>> cols["x"][2], cols["y"][2], cols["vx"][2] = -8.0, 4.0, 3.0  # right lane, behind
        >>> f = NeighbourFeatures(layout)(layout.encode(cols))
        >>> [round(v, 2) for v in f[12:15].tolist()]  # own lane: exists, leader gap, closing
        [1.0, 0.4, 0.5]
        >>> [round(v, 2) for v in f[26:28].tolist() + f[29:].tolist()]  # right lane's follower
        [0.06, 0.3, 1.0]
    """

    n_features = 30

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` to ``[*batch, 30]``."""
        scene = self.scene(observation)
        ego_y = self.layout.decode(observation.float())["y"][..., 0]
        offset_in_lane = ego_y - scene.lane.float() * self.layout.lane_width
        features = [
            (scene.speed - self.speed_centre) / self.speed_scale,
            offset_in_lane / 2.0,
            scene.ego_drift.float(),
        ]
        for lane in (-1, 0, 1):
            first_gap, first_closing = _nearest(scene, lane, ahead=True, rank=0)
            second_gap, second_closing = _nearest(scene, lane, ahead=True, rank=1)
            rear_gap, rear_closing = _nearest(scene, lane, ahead=False, rank=0)
            features += [scene.lane_exists(lane).float()]
            for gap, closing in (
                (first_gap, first_closing),
                (second_gap, second_closing),
                (rear_gap, rear_closing),
            ):
                features += [gap / 50.0, closing / 10.0]
            features += [
                _inverse_ttc(first_gap, first_closing),
                _inverse_ttc(rear_gap, rear_closing),
            ]
        return torch.stack(features, -1)


class NeighbourMLP(FeatureMLP):
    """An MLP over :class:`NeighbourFeatures`.

    Args:
        layout: how the observation is laid out.
        out_features: size of the output (actions for logits, 1 for a value).
        num_cells: widths of the hidden layers.
        activation_class: activation between hidden layers.
        target_speeds: the env's target speeds (see :class:`NeighbourFeatures`).

    Example:
        >>> from torchrl_grpo.modules import KinematicsLayout
        >>> net = NeighbourMLP(KinematicsLayout(), out_features=5, num_cells=(32,))
        >>> net(torch.zeros(4, 2, 5, 5)).shape
        torch.Size([4, 2, 5])
    """

    features_class = NeighbourFeatures


def build_neighbours(model_cfg: DictConfig, env: EnvBase, out_features: int) -> nn.Module:
    """``model.kind=neighbours``: a :class:`NeighbourMLP` of ``model.num_cells`` for ``env``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> cfg = OmegaConf.create({"kind": "neighbours", "num_cells": [8]})
        >>> type(build_neighbours(cfg, HighwayEnv(seed=0), 5)).__name__
        'NeighbourMLP'
    """
    return make_feature_mlp(NeighbourMLP, model_cfg, env, out_features)


register_network_kind(get_args(NeighboursKind)[0], build_neighbours, MLPModelConfig)
