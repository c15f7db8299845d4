"""Policy and value networks over highway-env's Kinematics observation table.

Both networks read a float tensor of shape ``[*batch, V, F]`` (V observed vehicles, F
features per vehicle, row 0 the ego vehicle) and return ``[*batch, out_features]``. They
are plain :class:`torch.nn.Module` objects: wrap them with the builders of
:mod:`torchrl_grpo.modules.actors` to get TorchRL actors and critics.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import torch
from torch import nn
from torchrl.modules import MLP

from torchrl_grpo.modules.vehicle_transformer import VehicleTransformer

__all__ = ["EgoAttentionNet", "KinematicsMLP", "NetworkKind", "make_network"]

NetworkKind = Literal["mlp", "ego_attention", "transformer"]


class KinematicsMLP(nn.Module):
    """An MLP over the flattened ``[V, F]`` vehicle table.

    Args:
        n_vehicles: number of rows V of the observation (highway-env's
            ``vehicles_count``).
        n_features: number of columns F (``len(features)``).
        out_features: size of the output (number of actions for logits, twice the
            action dimension for a location and a scale, 1 for a value).
        num_cells: widths of the hidden layers.
        activation_class: activation between hidden layers.

    Example:
        >>> net = KinematicsMLP(n_vehicles=5, n_features=5, out_features=3)
        >>> net(torch.zeros(4, 2, 5, 5)).shape
        torch.Size([4, 2, 3])
    """

    def __init__(
        self,
        n_vehicles: int,
        n_features: int,
        out_features: int,
        num_cells: Sequence[int] = (256, 256),
        activation_class: type[nn.Module] = nn.Tanh,
    ) -> None:
        super().__init__()
        self.n_vehicles = n_vehicles
        self.n_features = n_features
        self.mlp = MLP(
            in_features=n_vehicles * n_features,
            out_features=out_features,
            num_cells=list(num_cells),
            activation_class=activation_class,
        )

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` to ``[*batch, out_features]``."""
        _check_table(observation, self.n_features, self.n_vehicles)
        return self.mlp(observation.flatten(-2))


class EgoAttentionNet(nn.Module):
    """Ego-attention network of Leurent & Mercier (2019).

    From "Social Attention for Autonomous Decision-Making in Dense Traffic", as in
    rl-agents' ``EgoAttentionNetwork``. Every vehicle row goes through one shared
    encoder MLP. The ego embedding (row 0) is the single query of a multi-head
    attention over the embeddings of all rows (the ego included); vehicles whose
    presence feature is below 0.5 are masked out. As in rl-agents, the attention
    output is averaged with the ego embedding (a residual) and fed to a decoder MLP.
    The result depends neither on the order of the other vehicles nor on the
    features of absent ones.

    Args:
        n_features: number of columns F of the observation.
        out_features: size of the output.
        embed_dim: width of the vehicle embeddings and of the attention.
        num_heads: number of attention heads (must divide ``embed_dim``).
        encoder_cells: hidden widths of the per-vehicle encoder (its output has
            ``embed_dim`` units).
        decoder_cells: hidden widths of the decoder.
        presence_index: column of the presence feature; ``None`` attends to every row.
        activation_class: activation of the encoder and decoder MLPs.
        n_vehicles: if given, inputs must have exactly this many rows (any count works
            otherwise).

    Example:
        >>> net = EgoAttentionNet(n_features=5, out_features=3, embed_dim=16, num_heads=2)
        >>> obs = torch.zeros(2, 3, 4, 5, 5)  # e.g. [rollouts, groups, steps, V, F]
        >>> obs[..., 0, 0] = 1.0  # the ego is present
        >>> net(obs).shape
        torch.Size([2, 3, 4, 3])
    """

    def __init__(
        self,
        n_features: int,
        out_features: int,
        embed_dim: int = 64,
        num_heads: int = 2,
        encoder_cells: Sequence[int] = (64,),
        decoder_cells: Sequence[int] = (64, 64),
        presence_index: int | None = 0,
        activation_class: type[nn.Module] = nn.ReLU,
        n_vehicles: int | None = None,
    ) -> None:
        super().__init__()
        if embed_dim % num_heads:
            raise ValueError(f"num_heads={num_heads} must divide embed_dim={embed_dim}.")
        if presence_index is not None and not -n_features <= presence_index < n_features:
            raise ValueError(f"presence_index={presence_index} out of range for {n_features}.")
        self.n_features = n_features
        self.n_vehicles = n_vehicles
        self.presence_index = presence_index
        self.encoder = MLP(
            in_features=n_features,
            out_features=embed_dim,
            num_cells=list(encoder_cells),
            activation_class=activation_class,
            activate_last_layer=True,
        )
        # rl-agents' EgoAttention projects keys, queries and values without biases.
        self.attention = nn.MultiheadAttention(embed_dim, num_heads, bias=False, batch_first=True)
        self.decoder = MLP(
            in_features=embed_dim,
            out_features=out_features,
            num_cells=list(decoder_cells),
            activation_class=activation_class,
        )

    def attention_weights(self, observation: torch.Tensor) -> torch.Tensor:
        """Returns the ego's attention over the rows, ``[*batch, num_heads, V]``.

        Useful to visualise which vehicles the policy looks at.
        """
        _, weights = self._attend(observation, need_weights=True)
        return weights

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` to ``[*batch, out_features]``."""
        embedding, _ = self._attend(observation, need_weights=False)
        return self.decoder(embedding)

    def _attend(
        self, observation: torch.Tensor, need_weights: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        _check_table(observation, self.n_features, self.n_vehicles)
        batch_shape = observation.shape[:-2]
        n_rows = observation.shape[-2]
        # nn.MultiheadAttention takes exactly one batch dimension.
        flat = observation.reshape(batch_shape.numel(), n_rows, self.n_features)
        embedded = self.encoder(flat)
        if flat.shape[0] == 0:
            # nn.MultiheadAttention cannot reshape an empty batch.
            empty = embedded.new_zeros(*batch_shape, embedded.shape[-1])
            heads = self.attention.num_heads
            return empty, embedded.new_zeros(*batch_shape, heads, n_rows)
        ego = embedded[:, :1]
        mask = None
        if self.presence_index is not None:
            mask = flat[..., self.presence_index] < 0.5
            # The ego always attends to itself: padded steps (all-zero tables after an
            # episode ends) would otherwise mask every key and produce NaNs that leak
            # into masked losses (NaN * 0 = NaN).
            mask[:, 0] = False
        attended, weights = self.attention(
            ego,
            embedded,
            embedded,
            key_padding_mask=mask,
            need_weights=need_weights,
            average_attn_weights=False,
        )
        out = (attended.squeeze(1) + ego.squeeze(1)) / 2
        out = out.reshape(*batch_shape, out.shape[-1])
        if weights is not None:
            weights = weights.squeeze(-2).reshape(*batch_shape, weights.shape[1], n_rows)
        return out, weights


def make_network(
    kind: NetworkKind,
    *,
    n_vehicles: int,
    n_features: int,
    out_features: int,
    **kwargs: Any,
) -> nn.Module:
    """Builds a network by name, for config-driven construction.

    Args:
        kind: ``"mlp"`` for :class:`KinematicsMLP`, ``"ego_attention"`` for
            :class:`EgoAttentionNet`, ``"transformer"`` for
            :class:`~torchrl_grpo.modules.vehicle_transformer.VehicleTransformer`.
        n_vehicles: rows V of the observation.
        n_features: columns F of the observation.
        out_features: size of the output.
        **kwargs: forwarded to the network's constructor.

    Returns:
        The network.

    Example:
        >>> net = make_network("ego_attention", n_vehicles=5, n_features=5, out_features=5)
        >>> type(net).__name__
        'EgoAttentionNet'
    """
    if kind == "mlp":
        return KinematicsMLP(n_vehicles, n_features, out_features, **kwargs)
    if kind == "ego_attention":
        return EgoAttentionNet(n_features, out_features, n_vehicles=n_vehicles, **kwargs)
    if kind == "transformer":
        return VehicleTransformer(n_features, out_features, **kwargs)
    raise ValueError(
        f"Unknown network kind {kind!r}; expected 'mlp', 'ego_attention' or 'transformer'."
    )


def _check_table(observation: torch.Tensor, n_features: int, n_vehicles: int | None) -> None:
    # A clear message here beats a shape error deep inside a Linear layer.
    if observation.ndim < 2 or observation.shape[-1] != n_features:
        raise ValueError(
            f"Expected an observation of shape [*batch, V, {n_features}], got "
            f"{tuple(observation.shape)}."
        )
    if n_vehicles is not None and observation.shape[-2] != n_vehicles:
        raise ValueError(
            f"Expected {n_vehicles} vehicle rows, got {observation.shape[-2]} "
            f"(shape {tuple(observation.shape)})."
        )
