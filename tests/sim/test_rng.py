"""The counter-based streams: uniform, reproducible, independent of the batch around a row."""

import torch

from torchrl_grpo.sim.rng import DRAWS_PER_CALL, mix64, seed_keys, uniform


def splitmix_finaliser(x: int) -> int:
    """SplitMix64's finaliser in Python integers (an independent reference)."""
    mask = (1 << 64) - 1
    x &= mask
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & mask
    x ^= x >> 31
    return x - (1 << 64) if x >= 1 << 63 else x


def test_mix64_is_splitmix64s_finaliser():
    values = [0, 1, 12345, -1, 2**62, -(2**63)]
    assert mix64(torch.tensor(values)).tolist() == [splitmix_finaliser(v) for v in values]


def test_draws_are_uniform_and_in_range():
    keys = seed_keys(torch.arange(8), seed=3)
    u, _ = uniform(keys, torch.zeros(8, dtype=torch.int64), 20000)
    assert bool((u >= 0).all() and (u < 1).all())
    assert (u.mean(1) - 0.5).abs().max() < 0.01
    assert (u.var(1) - 1 / 12).abs().max() < 0.002
    # Neighbouring draws are uncorrelated.
    corr = torch.corrcoef(torch.stack([u[:, :-1].flatten(), u[:, 1:].flatten()]))[0, 1]
    assert abs(float(corr)) < 0.01


def test_a_row_draws_the_same_whatever_the_batch():
    keys = seed_keys(torch.arange(10), seed=0)
    counters = torch.arange(10, dtype=torch.int64)
    all_rows, _ = uniform(keys, counters, 7)
    alone, counter = uniform(keys[4:5], counters[4:5], 7)
    assert torch.equal(all_rows[4:5], alone) and counter.tolist() == [5]


def test_successive_calls_and_seeds_differ():
    keys = seed_keys(torch.arange(2), seed=0)
    first, counter = uniform(keys, torch.zeros(2, dtype=torch.int64), 4)
    second, _ = uniform(keys, counter, 4)
    other, _ = uniform(seed_keys(torch.arange(2), seed=1), torch.zeros(2, dtype=torch.int64), 4)
    assert not torch.equal(first, second) and not torch.equal(first, other)
    assert not torch.equal(first[0], first[1])


def test_too_many_draws_is_an_error():
    import pytest

    with pytest.raises(ValueError, match="draws"):
        uniform(
            torch.zeros(1, dtype=torch.int64), torch.zeros(1, dtype=torch.int64), DRAWS_PER_CALL + 1
        )
