"""bench_label_errors: which decisions its labels flag, and its labels in chunks."""

import doctest

import bench_label_errors as bench
import pytest
import torch
from omegaconf import OmegaConf

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import ConstantActionPolicy
from torchrl_grpo.training.algos.search_distill import search_labels
from torchrl_grpo.training.transfer import tensor_episodes

pytestmark = pytest.mark.experimental


def test_the_docstring_examples_run():
    assert doctest.testmod(bench).failed == 0


def test_a_flag_needs_the_action_to_crash_and_another_not_to():
    crashed = torch.tensor([[1, 0, 0], [1, 1, 1], [0, 1, 0], [0, 0, 0]], dtype=torch.bool)
    assert bench.flagged(crashed, torch.tensor([0, 1, 1, 2])).tolist() == [
        True,  # its branch crashes, two others do not
        False,  # every branch crashes: nothing to learn there
        True,
        False,  # no branch crashes
    ]


def test_the_labels_in_chunks_are_the_labels_in_one():
    cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}, "max_episode_steps": 3})
    data, steps = tensor_episodes(
        cfg, ConstantActionPolicy("FASTER"), episodes=4, seed=50, return_state=True
    )
    states = data[steps]
    tail = ConstantActionPolicy("IDLE")
    whole = search_labels(
        LookaheadPolicy(TensorHighwayEnv("highway-fast-v0", num_envs=5 * len(states)), tail, 2),
        states,
    )
    bench.CHUNK, chunk = 5, bench.CHUNK
    try:
        parts = bench.labelled(cfg, tail, states, horizon=2)
    finally:
        bench.CHUNK = chunk
    assert torch.equal(parts["search_scores"], whole["search_scores"])
    assert torch.equal(parts["search_crashed"], whole["search_crashed"])
