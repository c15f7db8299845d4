"""PolicyEnsemble against means computed by hand, and the member a block selects."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from torchrl_grpo.modules import CrashHead, PolicyEnsemble
from torchrl_grpo.modules.ensemble import member_halves


class _Constant(nn.Module):
    """Outputs ``values`` for every row of the input."""

    def __init__(self, values: list[float]) -> None:
        super().__init__()
        self.values = nn.Parameter(torch.tensor(values))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.values.expand(*observation.shape[:-1], -1)


def test_it_acts_with_the_members_mean_and_one_member_inside_acting():
    ensemble = PolicyEnsemble([_Constant([0.0, 3.0]), _Constant([6.0, 0.0]), _Constant([3.0, 3.0])])
    x = torch.zeros(4, 7)
    assert torch.equal(ensemble(x), torch.tensor([[3.0, 2.0]] * 4))
    with ensemble.acting(1):
        assert torch.equal(ensemble(x), torch.tensor([[6.0, 0.0]] * 4))
    assert ensemble.active is None
    # The block restores the mean even when it raises.
    with pytest.raises(RuntimeError), ensemble.acting(2):
        raise RuntimeError
    assert torch.equal(ensemble(x)[0], torch.tensor([3.0, 2.0]))


def test_only_the_active_member_gets_a_gradient():
    members = [_Constant([1.0, 2.0]), _Constant([3.0, 4.0])]
    ensemble = PolicyEnsemble(members)
    with ensemble.acting(0):
        ensemble(torch.zeros(1, 1)).sum().backward()
    assert torch.equal(members[0].values.grad, torch.ones(2))
    assert members[1].values.grad is None


def test_crash_heads_average_their_logits_and_crash_logits():
    # Member outputs: logits then crash logits (n_actions = 1); aversion 0 keeps logits.
    heads = [CrashHead(_Constant([2.0, 0.0]), 1), CrashHead(_Constant([4.0, math.log(3)]), 1)]
    ensemble = PolicyEnsemble(heads)
    x = torch.zeros(2, 1)
    assert torch.allclose(ensemble(x), torch.tensor([[3.0], [3.0]]))
    assert torch.allclose(ensemble.crash_logits(x), torch.full((2, 1), math.log(3) / 2))
    with ensemble.acting(1):
        assert torch.allclose(ensemble.crash_logits(x), torch.full((2, 1), math.log(3)))


def test_bad_input_is_refused_with_the_problem_named():
    with pytest.raises(ValueError, match="at least 2 members, got 1"):
        PolicyEnsemble([nn.Linear(1, 1)])
    ensemble = PolicyEnsemble([nn.Linear(1, 1), nn.Linear(1, 1)])
    with pytest.raises(IndexError, match="member 2 of an ensemble of 2"), ensemble.acting(2):
        pass
    with pytest.raises(TypeError, match="no crash_logits.*model.crash_head=true"):
        ensemble.crash_logits(torch.zeros(1, 1))
    assert ensemble.active is None


def test_member_halves_by_hand():
    # frac(g * a_k): a_0 = frac(sqrt 2) = 0.4142.., a_1 = frac(sqrt 3) = 0.7320..
    # g = 1: 0.414 | 0.732; g = 2: 0.828 | 0.464; g = 4: 0.657 | 0.928, in no half, so
    # it goes to member 4 mod 2 = 0.
    halves = member_halves(torch.tensor([0, 1, 2, 4]), 2)
    expected = torch.tensor([[True, True], [True, False], [False, True], [True, False]])
    assert torch.equal(halves, expected)
    assert member_halves(torch.tensor([[1, 2]]), 2).shape == (1, 2, 2)
    with pytest.raises(TypeError, match="group ids are integers"):
        member_halves(torch.tensor([1.0]), 2)
    with pytest.raises(ValueError, match="at least 1 member"):
        member_halves(torch.tensor([1]), 0)


def test_member_halves_are_even_and_independent():
    halves = member_halves(torch.arange(100_000), 4)
    # Each member: half of the groups, plus its share of the 1 in 16 in no half.
    share = halves.float().mean(0)
    assert torch.allclose(share, torch.full((4,), 0.5 + 1 / 64), atol=0.002)
    # Two members' halves overlap in a quarter of the groups, as independent halves do.
    both = (halves[:, 0] & halves[:, 1]).float().mean()
    assert abs(float(both) - 0.25) < 0.02
    assert bool(halves.any(-1).all())
