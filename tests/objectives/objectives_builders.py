"""Builders for the objectives tests: small actors and branch-group batches.

A plain module rather than conftest.py, whose name other test folders share.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor, TanhNormal, TruncatedNormal

OBS_DIM = 4
N_ACTIONS = 3
ACT_DIM = 2


class TableLogits(nn.Module):
    """One free row of logits per integer state: per-step gradients are readable."""

    def __init__(self, n_states: int, n_actions: int) -> None:
        super().__init__()
        self.table = nn.Parameter(torch.zeros(n_states, n_actions))

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.table[state]


def categorical_actor(obs_dim: int = OBS_DIM, n_actions: int = N_ACTIONS) -> ProbabilisticActor:
    net = nn.Sequential(nn.Linear(obs_dim, 16), nn.Tanh(), nn.Linear(16, n_actions))
    module = TensorDictModule(net, ["observation"], ["logits"])
    return ProbabilisticActor(
        module, ["logits"], distribution_class=torch.distributions.Categorical, return_log_prob=True
    )


def table_actor(n_states: int, n_actions: int = N_ACTIONS) -> ProbabilisticActor:
    module = TensorDictModule(TableLogits(n_states, n_actions), ["state"], ["logits"])
    return ProbabilisticActor(
        module, ["logits"], distribution_class=torch.distributions.Categorical, return_log_prob=True
    )


def continuous_actor(kind: str, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM):
    net = nn.Sequential(
        nn.Linear(obs_dim, 16), nn.Tanh(), nn.Linear(16, 2 * act_dim), NormalParamExtractor()
    )
    module = TensorDictModule(net, ["observation"], ["loc", "scale"])
    dist_class = {
        "tanh_normal": TanhNormal,
        "independent_normal": IndependentNormal,
        "normal": torch.distributions.Normal,
        "truncated_normal": TruncatedNormal,
    }[kind]
    bounded = kind in ("tanh_normal", "truncated_normal")
    kwargs = {"low": -1.0, "high": 1.0} if bounded else {}
    return ProbabilisticActor(
        module,
        ["loc", "scale"],
        distribution_class=dist_class,
        distribution_kwargs=kwargs,
        return_log_prob=True,
    )


def branch_batch(
    actor: ProbabilisticActor,
    shape: tuple[int, int, int],
    *,
    seed: int = 0,
    obs_key: str = "observation",
    obs_dim: int = OBS_DIM,
    behaviour_noise: float = 0.3,
    masked: bool = False,
) -> TensorDict:
    """A ``[R, G, T]`` batch acted by ``actor`` whose stored log-probs are perturbed.

    The perturbation makes the importance ratios differ from one, so that clipping
    actually happens. With ``masked``, each branch has a random length >= 1.
    """
    gen = torch.Generator().manual_seed(seed)
    R, G, T = shape
    obs = torch.randn(R, G, T, obs_dim, generator=gen)
    td = TensorDict({obs_key: obs}, batch_size=shape)
    with torch.no_grad():
        td = actor(td)
    lp_key = actor.log_prob_keys[0]
    lp = td[lp_key]
    td[lp_key] = lp + behaviour_noise * torch.randn(lp.shape, generator=gen)
    td["advantage"] = torch.randn(R, G, T, 1, generator=gen)
    td["group_id"] = torch.arange(R).view(R, 1, 1).expand(R, G, T).clone()
    td["branch"] = torch.arange(G).view(1, G, 1).expand(R, G, T).clone()
    td["next", "reward"] = torch.randn(R, G, T, 1, generator=gen)
    if masked:
        lengths = torch.randint(1, T + 1, (R, G, 1), generator=gen)
        td["mask"] = torch.arange(T).view(1, 1, T) < lengths
    else:
        td["mask"] = torch.ones(R, G, T, dtype=torch.bool)
    return td.detach()
