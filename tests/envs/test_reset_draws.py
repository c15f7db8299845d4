"""The reset draws replayed from highway-env's generator words, against numpy's own calls.

merge-v0's in C++ (sim/pcg64.h), roundabout-v0's destination drawn as ``integers``
where highway-env calls ``choice``: each bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrl_grpo.envs import StateCorruptedError, TensorHighwayEnv
from torchrl_grpo.envs.core.gym_state import encode_rng, restore_rng, seeded_rng_words
from torchrl_grpo.envs.highway.merge_bridge import merge_draws, native_merge_draws
from torchrl_grpo.envs.highway.roundabout_bridge import roundabout_draws
from torchrl_grpo.envs.highway.tensor_params import tensor_params


def generator_words(count: int) -> torch.Tensor:
    """Seeded generators, every third one a 32-bit draw further on (``has_uint32`` = 1)."""
    words = torch.stack([seeded_rng_words(s) for s in range(count)]).numpy().copy()
    generator = np.random.default_rng()
    for row in range(0, count, 3):
        restore_rng(generator, words[row])
        generator.integers(2)
        encode_rng(generator, words[row])
    return torch.from_numpy(words)


def test_the_draws_and_the_words_after_are_numpys():
    words = generator_words(600)
    assert (words[:, 8] == 1).any() and (words[:, 8] == 0).any()
    rows = torch.rand(600, generator=torch.Generator().manual_seed(0)) < 0.7
    draws, after = native_merge_draws(words, rows)
    expected_draws, expected_after = merge_draws(words, rows)
    assert torch.equal(draws, expected_draws) and torch.equal(after, expected_after)
    assert torch.equal(after[~rows], words[~rows]) and not torch.equal(after[rows], words[rows])
    # By hand, highway-env's seed 0: lane 1, -2.30 m, -0.92 m/s for the first car.
    first, _ = native_merge_draws(seeded_rng_words(0).unsqueeze(0), torch.tensor([True]))
    assert first[0, :3].tolist() == [1.0, -2.302132862361297, -0.9180529521276106]


def test_corrupted_words_are_refused_by_row_as_numpys_replay_refuses_them():
    words = generator_words(4)
    words[2, 4] += 1  # an even increment: no state numpy makes
    rows = torch.tensor([True, False, True, True])
    with pytest.raises(StateCorruptedError, match="highway.rng of row 2: the PCG64 increment"):
        native_merge_draws(words, rows)
    with pytest.raises(StateCorruptedError, match="highway.rng of row 2: the PCG64 increment"):
        merge_draws(words, rows)
    native_merge_draws(words, torch.tensor([True, True, False, True]))  # row 2 not reset
    with pytest.raises(ValueError, match=r"\[B, 10\] with \[B\] rows, got \(4, 9\)"):
        native_merge_draws(words[:, :9], rows)


def test_the_cpp_step_resets_merge_worlds_as_the_tensor_step_does():
    native = TensorHighwayEnv("merge-v0", num_envs=64, seed=5, native=True)
    tensor = TensorHighwayEnv("merge-v0", num_envs=64, seed=5)
    assert torch.equal(native.reset()["observation"], tensor.reset()["observation"])
    actions = torch.randint(0, 5, (12, 64), generator=torch.Generator().manual_seed(1))
    a, b, ended = native.reset(), tensor.reset(), 0
    for action in actions:  # random actions crash and end episodes: many resets
        out, a = native.step_and_maybe_reset(a.set("action", action))
        ended += int(out["next", "done"].sum())
        b = tensor.step_and_maybe_reset(b.set("action", action))[1]
    assert ended >= 20
    assert torch.equal(native.get_state()["highway", "rng"], tensor.get_state()["highway", "rng"])


def test_the_roundabouts_draws_are_those_of_highway_envs_choice():
    params = tensor_params("roundabout-v0")
    names = [params.road.destinations[d] for d in params.traffic.destinations]
    low, high = params.idm.delta_range
    words = generator_words(300)
    draws, after = roundabout_draws(words, torch.ones(300, dtype=torch.bool), params)
    generator = np.random.default_rng()
    for row in range(300):
        restore_rng(generator, words[row].numpy())
        expected = []
        for _ in range(4):  # RoundaboutEnv._make_vehicles' calls, choice as it makes it
            expected += [generator.normal(), generator.normal()]
            expected += [float(names.index(str(generator.choice(names))))]
            expected += [generator.uniform(low=low, high=high)]
        assert draws[row].tolist() == expected
        state = np.zeros(10, dtype=np.int64)
        encode_rng(generator, state)
        assert after[row].tolist() == state.tolist()
