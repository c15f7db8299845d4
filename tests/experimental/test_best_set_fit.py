"""Where roots look alike, the core's regret fit and the lab's best-set cross-entropy part ways."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "objectives"))

from test_regret_fit import _fitted_probability_of_action_0  # noqa: E402

import torchrl_grpo.experimental  # noqa: E402, F401  (registers the cross-entropy fit)

pytestmark = pytest.mark.experimental


def test_the_best_set_cross_entropy_splits_where_the_regret_fit_does_not():
    # Action 0 costs 0 and 1 in the two roots, action 1 costs 10 and 0: the regret fit
    # plays action 0; each action is best once, so the best-set fit splits them evenly.
    assert _fitted_probability_of_action_0("regret") > 0.9
    assert _fitted_probability_of_action_0("cross_entropy") == pytest.approx(0.5, abs=0.02)
