"""bench_crash_foresight's scoring of the decisions before each crash, worked by hand."""

import doctest

import bench_crash_foresight as bench
import pytest
import torch

pytestmark = pytest.mark.experimental


def test_the_docstring_example_runs():
    assert doctest.testmod(bench).failed == 0


def test_rows_count_each_crash_once_and_only_steps_of_the_episode():
    # Three episodes, four steps, two actions.
    p = torch.tensor(
        [
            [[0.15, 0.0], [0.25, 0.1], [0.5, 0.1], [0.9, 0.9]],  # crashes at step 2 (then padding)
            [[0.3, 0.3], [0.4, 0.2], [0.0, 0.0], [0.0, 0.0]],  # crashes at step 0
            [[0.0, 0.2], [0.0, 0.2], [0.0, 0.2], [0.0, 0.2]],  # never crashes
        ]
    )
    action = torch.tensor([[0, 0, 0, 1], [1, 0, 0, 0], [0, 0, 0, 0]])
    steps = torch.tensor([[1, 1, 1, 0], [1, 0, 0, 0], [1, 1, 1, 1]], dtype=torch.bool)
    # A crash flagged on a step after the episode's end is not the episode's.
    crashed = torch.tensor([[0, 0, 1, 1], [1, 0, 0, 0], [0, 0, 0, 0]], dtype=torch.bool)
    rows = bench.foresight(p, action, steps, crashed, look_back=3, margin=0.1)
    assert [r.k for r in rows] == [None, 0, 1, 2]
    everything, last, one, two = rows
    # All 8 steps of the episodes: chosen 0.15 0.25 0.5 | 0.3 | 0 0 0 0.
    assert everything.count == 8
    assert everything.chosen == pytest.approx(1.2 / 8)
    assert everything.safest == pytest.approx((0.0 + 0.1 + 0.1 + 0.3) / 8)
    assert everything.avoidable == pytest.approx(3 / 8)  # episode 0's three steps
    # The last decision of each crash: episode 0's step 2 and episode 1's step 0.
    assert (last.count, last.chosen, last.safest) == (2, pytest.approx(0.4), pytest.approx(0.2))
    assert last.avoidable == pytest.approx(0.5)
    # Only episode 0 has decisions before its crash.
    assert (one.count, one.chosen, one.safest, one.avoidable) == (
        1,
        pytest.approx(0.25),
        pytest.approx(0.1),
        1.0,
    )
    assert (two.count, two.chosen, two.safest, two.avoidable) == (
        1,
        pytest.approx(0.15),
        pytest.approx(0.0),
        1.0,
    )


def test_no_crash_leaves_the_look_back_rows_empty():
    p = torch.full((2, 3, 5), 0.25)
    ones = torch.ones(2, 3, dtype=torch.bool)
    rows = bench.foresight(p, torch.zeros(2, 3, dtype=torch.long), ones, ~ones, look_back=2)
    assert rows[0].count == 6 and rows[0].chosen == pytest.approx(0.25)
    assert [r.count for r in rows[1:]] == [0, 0]
