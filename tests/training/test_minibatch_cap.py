"""``algo.max_minibatches``: at most ``epochs`` passes and at most ``k`` minibatches a batch."""

from __future__ import annotations

from collections import Counter

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torch import nn
from train_setup import TINY, compose_config

from torchrl_grpo.training import Algorithm


class _Recorder(nn.Module):
    """A loss that records the steps of every minibatch it is given."""

    def __init__(self) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(()))
        self.seen: list[list[int]] = []

    def forward(self, minibatch):
        self.seen.append(minibatch.get("index").tolist())
        return TensorDict(loss_objective=(self.weight - 1.0) ** 2)


class _Counting(Algorithm):
    @classmethod
    def make_loss(cls, algo_cfg, policy, value=None):
        return _Recorder()


def _minibatches(cap, n=100, minibatch_size=10, epochs=2):
    algo = {"epochs": epochs, "minibatch_size": minibatch_size, "max_minibatches": cap}
    cfg = OmegaConf.create(
        {
            "algo": algo,
            "model": {},
            "optim": {"lr": 0.1, "weight_decay": 0.0, "eps": 1e-8, "max_grad_norm": 1.0},
        }
    )
    algorithm = _Counting(cfg, nn.Linear(1, 1), env=None)
    stats = algorithm.optimise(TensorDict(index=torch.arange(n), batch_size=[n]))
    seen = algorithm.loss.seen
    assert stats["train/minibatches"] == len(seen) == algorithm.updates
    assert all(len(mb) == minibatch_size for mb in seen)
    return seen


def test_without_a_cap_every_step_is_seen_once_per_epoch():
    seen = _minibatches(None)
    assert len(seen) == 20
    assert Counter(i for mb in seen for i in mb) == Counter({i: 2 for i in range(100)})


def test_a_cap_below_one_pass_trains_on_a_random_subset_without_repeats():
    seen = _minibatches(5)
    steps = [i for mb in seen for i in mb]
    assert len(seen) == 5 and len(set(steps)) == 50
    # A random subset, not the first 50 steps.
    assert set(steps) != set(range(50))


def test_a_cap_past_one_pass_finishes_the_first_pass_then_stops_in_the_second():
    seen = _minibatches(15)
    first, second = seen[:10], seen[10:]
    assert sorted(i for mb in first for i in mb) == list(range(100))
    assert len(second) == 5 and len({i for mb in second for i in mb}) == 50


def test_the_epochs_still_bound_a_large_cap():
    assert len(_minibatches(1000)) == 20


def test_a_cap_below_one_is_refused():
    cfg = compose_config([*TINY, "algo=grpo_lab", "algo.max_minibatches=0"])
    with pytest.raises(ValueError, match="algo.max_minibatches must be >= 1"):
        Algorithm.check_config(cfg)
