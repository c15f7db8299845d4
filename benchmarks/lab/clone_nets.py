"""Networks for cloning the search: four trunks, and a crash head beside the policy.

Each :class:`CloneNet` maps the flat Kinematics table ``[N, V * F]`` (what
``search_clone_scale.py`` fits and drives) to the logits of the action it would take.
Its trunk reads the table one of four ways (:func:`make_trunk`):

* ``flat``: an MLP over the standardised table, as ``label_inputs.fit``;
* ``scene``: the same MLP over the table and the 18 driving features of
  :class:`~torchrl_grpo.modules.SceneFeatures` (gaps, closing speeds, room to change
  lane), the features the runs' own networks read;
* ``attention``: the ego-attention network (one encoder shared by every vehicle,
  :class:`~torchrl_grpo.modules.networks.EgoAttentionNet`), which learns one function of
  a vehicle for all the rows, whatever order the distance puts them in;
* ``transformer``: layers of self-attention among the vehicles (two unless told)
  before the ego reads them out, so that a car's reaction to the car ahead of it can
  be composed.

With a crash head the net has a second output per action: the logit of the chance that
the action's branch crashes within the horizon, fitted to the search's crash flags. It
acts on ``policy + aversion * log(1 - p_crash)``, as the runs' crash heads do, and bars
the actions whose ``p_crash`` exceeds the smallest by more than ``margin``.

Example:
    >>> from torchrl_grpo.modules.kinematics_table import KinematicsLayout
    >>> x = torch.zeros(8, 25)
    >>> net = CloneNet(make_trunk("scene", KinematicsLayout(), x, 32), 32, 5, crash_head=True)
    >>> net.aversion = 3.0
    >>> net(x).shape, net.heads(x)[1].shape
    (torch.Size([8, 5]), torch.Size([8, 5]))
"""

from __future__ import annotations

import torch
from label_inputs import _Standardise
from torch import nn
from torch.nn import functional as F

from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.modules.networks import EgoAttentionNet
from torchrl_grpo.modules.scene_features import SceneFeatures

TRUNKS = ("flat", "scene", "attention", "transformer")


class _Table(nn.Module):
    """The flat table back as ``[N, V, F]`` rows, its feature columns standardised.

    The presence column stays 0 or 1: the attention masks absent vehicles with it.
    """

    def __init__(self, layout: KinematicsLayout, x: torch.Tensor) -> None:
        super().__init__()
        self.shape = (layout.n_vehicles, layout.n_features)
        rows = x.reshape(-1, *self.shape)
        present = rows[..., layout.index("presence")] > 0.5
        mean, std = rows[present].mean(0), rows[present].std(0) + 1e-6
        keep = torch.arange(self.shape[1]) == layout.index("presence")
        self.register_buffer("mean", torch.where(keep, 0.0, mean))
        self.register_buffer("std", torch.where(keep, 1.0, std))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x.reshape(-1, *self.shape) - self.mean) / self.std


class _SceneAndTable(nn.Module):
    """The driving features beside the standardised flat table."""

    def __init__(self, layout: KinematicsLayout, x: torch.Tensor) -> None:
        super().__init__()
        self.shape = (layout.n_vehicles, layout.n_features)
        self.scene = SceneFeatures(layout)
        self.table = _Standardise(x.mean(0), x.std(0) + 1e-6)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scene = self.scene(x.reshape(-1, *self.shape))
        return torch.cat([scene, self.table(x)], -1)


class _VehicleTransformer(nn.Module):
    """Layers of self-attention among the vehicles, then the ego's row and their mean.

    A car's next seconds depend on the car ahead of it (IDM follows its leader), and that
    one's on the next: a single query from the ego weighs the vehicles but cannot compose
    such chains; layers of attention among them can.
    """

    def __init__(self, layout: KinematicsLayout, embed: int, width: int, layers: int) -> None:
        super().__init__()
        self.presence = layout.index("presence")
        self.encoder = nn.Sequential(
            nn.Linear(layout.n_features, embed), nn.ReLU(), nn.Linear(embed, embed)
        )
        layer = nn.TransformerEncoderLayer(
            embed, 4, dim_feedforward=2 * embed, dropout=0.0, batch_first=True
        )
        self.layers = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.decoder = nn.Sequential(nn.Linear(2 * embed, width), nn.Tanh())

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        absent = rows[..., self.presence] < 0.5
        absent[:, 0] = False  # the ego is always there, also in the zero rows of padding
        hidden = self.layers(self.encoder(rows), src_key_padding_mask=absent)
        present = (~absent).unsqueeze(-1).float()
        mean = (hidden * present).sum(1) / present.sum(1)
        return self.decoder(torch.cat([hidden[:, 0], mean], -1))


def _mlp(in_features: int, width: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_features, width), nn.Tanh(), nn.Linear(width, width), nn.Tanh()
    )


def make_trunk(
    kind: str,
    layout: KinematicsLayout,
    x: torch.Tensor,
    width: int,
    embed: int = 64,
    layers: int = 2,
) -> nn.Module:
    """A trunk from the flat table ``[N, V * F]`` to ``[N, width]`` hidden units.

    Args:
        kind: ``flat``, ``scene``, ``attention`` or ``transformer`` (the module's
            docstring).
        layout: the observation's layout.
        x: the states to be fitted, for the standardisation.
        width: the hidden units.
        embed: ``attention``, ``transformer``: the width of the vehicles' embeddings.
        layers: ``transformer``: its layers of self-attention.
    """
    if kind == "flat":
        return nn.Sequential(_Standardise(x.mean(0), x.std(0) + 1e-6), _mlp(x.shape[1], width))
    if kind == "scene":
        return nn.Sequential(
            _SceneAndTable(layout, x), _mlp(SceneFeatures.n_features + x.shape[1], width)
        )
    if kind == "attention":
        attention = EgoAttentionNet(
            layout.n_features,
            width,
            embed_dim=embed,
            num_heads=4,
            encoder_cells=(embed,),
            decoder_cells=(width,),
            presence_index=layout.index("presence"),
        )
        return nn.Sequential(_Table(layout, x), attention, nn.Tanh())
    if kind == "transformer":
        return nn.Sequential(_Table(layout, x), _VehicleTransformer(layout, embed, width, layers))
    raise ValueError(f"unknown trunk {kind!r}; expected one of {TRUNKS}")


class CloneNet(nn.Module):
    """A trunk, the policy's logits and optionally a crash head (the module's docstring).

    Args:
        trunk: from the flat table to ``width`` hidden units (:func:`make_trunk`).
        width: the trunk's output size.
        actions: the number of actions.
        crash_head: whether to add the crash head.
    """

    def __init__(self, trunk: nn.Module, width: int, actions: int, crash_head: bool) -> None:
        super().__init__()
        self.trunk = trunk
        self.policy = nn.Linear(width, actions)
        self.crash = nn.Linear(width, actions) if crash_head else None
        self.aversion = 0.0
        self.margin: float | None = None

    def heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The policy's logits and the crash logits (``None`` without a crash head), each
        ``[*batch, actions]`` for ``x`` of ``[*batch, V * F]`` (an unbatched env's ``[V * F]``
        gives ``[actions]``)."""
        hidden = self.trunk(x.reshape(-1, x.shape[-1]))
        hidden = hidden.reshape(*x.shape[:-1], hidden.shape[-1])
        return self.policy(hidden), None if self.crash is None else self.crash(hidden)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The logits the net acts on: the policy's, weighed and barred by the crash head."""
        logits, crash = self.heads(x)
        return act_logits(logits, crash, self.aversion, self.margin)


def act_logits(
    logits: torch.Tensor, crash: torch.Tensor | None, aversion: float, margin: float | None
) -> torch.Tensor:
    """``logits + aversion * log(1 - p_crash)``, the actions beyond ``margin`` barred."""
    if crash is None:
        return logits
    acted = logits + aversion * F.logsigmoid(-crash)
    if margin is not None:
        p = crash.sigmoid()
        barred = p > p.amin(-1, keepdim=True) + margin
        acted = acted.masked_fill(barred, float("-inf"))
    return acted
