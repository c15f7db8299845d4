"""bench_barring_heads: one head is the policy's own greedy choice; another head bars."""

import bench_barring_heads as bench
import pytest
import torch
from tensordict import TensorDict
from torch import nn

from torchrl_grpo.modules.crash_head import CrashHead

pytestmark = pytest.mark.experimental


def head(logits: list[float], risks: list[float]) -> CrashHead:
    """A head whose outputs are fixed: these policy logits and crash probabilities."""
    net = nn.Linear(3, 10)
    with torch.no_grad():
        net.weight.zero_()
        net.bias.copy_(torch.tensor(logits + torch.logit(torch.tensor(risks)).tolist()))
    out = CrashHead(net, 5)
    out.set_margin(0.01, bench.SLOWER)
    return out


def test_one_head_plays_its_own_greedy_choice_and_another_head_bars():
    obs = TensorDict(observation=torch.zeros(2, 3), batch_size=[2])
    own = head([0.0, 1.0, 0.0, 3.0, 0.0], [0.01, 0.01, 0.01, 0.015, 0.01])
    assert bench.BarredGreedy([own])(obs.clone())["action"].tolist() == [3, 3]
    # Its own margin: FASTER at 0.03 is 0.02 riskier than SLOWER, barred; IDLE is next.
    wary = head([0.0, 1.0, 0.0, 3.0, 0.0], [0.01, 0.01, 0.01, 0.03, 0.01])
    assert bench.BarredGreedy([wary])(obs.clone())["action"].tolist() == [1, 1]
    # A second head that finds FASTER and IDLE dangerous bars both of them.
    other = head([0.0] * 5, [0.01, 0.5, 0.01, 0.5, 0.01])
    assert bench.BarredGreedy([own, other])(obs.clone())["action"].tolist() == [0, 0]
    # Where a head finds every other action dangerous, SLOWER is what is left.
    alarmed = head([0.0] * 5, [0.9, 0.9, 0.9, 0.9, 0.1])
    assert bench.BarredGreedy([own, alarmed])(obs.clone())["action"].tolist() == [4, 4]
