"""Layers of self-attention among the observed vehicles: the network of ``model=transformer``.

The ego-attention network (:class:`~torchrl_grpo.modules.networks.EgoAttentionNet`) has
one query, the ego's: it weighs the vehicles but cannot compose a chain, such as a car
braking for the car ahead of it, which brakes for the next. Layers of attention among
the vehicles can. Fitted to the lookahead search's labels, two such layers err into
crashes a sixth less often than the ego-attention network at the same steps
(docs/lab/targets.md, "An attention network with a crash head").
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["VehicleTransformer"]


class VehicleTransformer(nn.Module):
    """Rows of ``[*batch, V, F]`` encoded, attended among, and read out at the ego and mean.

    Every row (vehicle) goes through one shared encoder, then ``layers`` layers of
    self-attention among the present rows (those whose presence feature is at least
    0.5; the ego, row 0, always). The ego's output row and the mean of the present
    rows feed a decoder with ``width`` tanh units. The features are standardised with
    statistics of the data the network is fitted on (:meth:`standardise_from`); until
    then they pass unchanged. The presence column is never standardised.

    Args:
        n_features: columns F of the observation.
        out_features: size of the output.
        presence_index: the column of the presence feature.
        embed_dim: width of the vehicles' embeddings.
        num_heads: attention heads (must divide ``embed_dim``).
        layers: layers of self-attention.
        width: the decoder's hidden units.

    Example:
        >>> net = VehicleTransformer(n_features=7, out_features=5, presence_index=0)
        >>> obs = torch.rand(4, 15, 7)
        >>> net(obs).shape, net(obs[0]).shape
        (torch.Size([4, 5]), torch.Size([5]))
        >>> net.standardise_from(obs)
        >>> bool(net.standardised)
        True
    """

    def __init__(
        self,
        n_features: int,
        out_features: int,
        presence_index: int,
        embed_dim: int = 64,
        num_heads: int = 4,
        layers: int = 2,
        width: int = 256,
    ) -> None:
        super().__init__()
        if embed_dim % num_heads:
            raise ValueError(f"num_heads={num_heads} must divide embed_dim={embed_dim}")
        if layers < 1:
            raise ValueError(f"layers must be >= 1, got {layers}")
        if not -n_features <= presence_index < n_features:
            raise ValueError(f"presence_index={presence_index} out of range for {n_features}")
        self.n_features = n_features
        self.presence_index = presence_index % n_features
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("std", torch.ones(n_features))
        self.register_buffer("standardised", torch.tensor(False))
        self.encoder = nn.Sequential(
            nn.Linear(n_features, embed_dim), nn.ReLU(), nn.Linear(embed_dim, embed_dim)
        )
        layer = nn.TransformerEncoderLayer(
            embed_dim, num_heads, dim_feedforward=2 * embed_dim, dropout=0.0, batch_first=True
        )
        self.layers = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.decoder = nn.Sequential(
            nn.Linear(2 * embed_dim, width), nn.Tanh(), nn.Linear(width, out_features)
        )

    @torch.no_grad()
    def standardise_from(self, observation: torch.Tensor) -> None:
        """Standardise the features from now on with the present rows of ``observation``.

        Raises:
            ValueError: ``observation`` is not ``[*batch, V, F]`` or shows no present row.
        """
        if observation.ndim < 2 or observation.shape[-1] != self.n_features:
            raise ValueError(
                f"expected an observation of shape [*batch, V, {self.n_features}], got "
                f"{tuple(observation.shape)}"
            )
        rows = observation.reshape(-1, self.n_features).to(self.mean)
        present = rows[rows[:, self.presence_index] >= 0.5]
        if present.shape[0] < 2:
            raise ValueError("standardise_from needs at least two present vehicle rows")
        keep = torch.arange(self.n_features, device=rows.device) == self.presence_index
        self.mean.copy_(torch.where(keep, 0.0, present.mean(0)))
        self.std.copy_(torch.where(keep, 1.0, present.std(0) + 1e-6))
        self.standardised.fill_(True)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` to ``[*batch, out_features]``."""
        if observation.ndim < 2 or observation.shape[-1] != self.n_features:
            raise ValueError(
                f"expected an observation of shape [*batch, V, {self.n_features}], got "
                f"{tuple(observation.shape)}"
            )
        batch = observation.shape[:-2]
        rows = observation.reshape(-1, *observation.shape[-2:])
        absent = rows[..., self.presence_index] < 0.5
        absent[:, 0] = False  # the ego is always there, also in a padding row of zeros
        hidden = self.layers(
            self.encoder((rows - self.mean) / self.std), src_key_padding_mask=absent
        )
        present = (~absent).unsqueeze(-1).to(hidden.dtype)
        mean = (hidden * present).sum(1) / present.sum(1)
        out = self.decoder(torch.cat([hidden[:, 0], mean], -1))
        return out.reshape(*batch, out.shape[-1])
