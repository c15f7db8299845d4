"""An end-to-end run of the experimental cross-entropy group fit: each group's target is
stored with its replayed rows, and the spread weighting scales it by the group's spread."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))

from train_helpers import REPLAY, csv_scalars, logged_ratios, train_run  # noqa: E402
from train_setup import TINY, compose_config  # noqa: E402

from torchrl_grpo.training import Trainer  # noqa: E402

pytestmark = pytest.mark.experimental


def test_distillation_stores_each_groups_target_and_trains_on_it(tmp_path):
    overrides = [*REPLAY, "algo.group_fit_coeff=2.0", "algo.group_fit_loss=cross_entropy"]
    overrides += ["algo.group_fit_temperature=0.0", "logger=csv"]
    trainer = train_run(tmp_path, "distill", [*overrides, "experiment.total_frames=60"])
    stored = trainer.algo.replay[:]
    weight, advantage = stored["distill_weight"].squeeze(-1), stored["advantage"].squeeze(-1)
    # A group's 5 rows are stored together; hard targets split its weight over its best.
    assert (stored["group_id"].reshape(-1, 5) == stored["group_id"].reshape(-1, 5)[:, :1]).all()
    advantage, weight = advantage.reshape(-1, 5), weight.reshape(-1, 5)
    best = (advantage == advantage.max(-1, keepdim=True).values).float()
    torch.testing.assert_close(weight, best / best.sum(-1, keepdim=True))
    assert weight.shape[0] >= 3 and bool((best.sum(-1) < 5).any())  # some groups disagree
    scalars = csv_scalars(tmp_path / "distill")
    assert len(scalars["train/loss_distill"]) == trainer.iteration
    ratios = logged_ratios(scalars, "train/loss_distill", "train/distill_cross_entropy")
    assert ratios == pytest.approx([2.0] * trainer.iteration)
    spread = train_run(
        tmp_path,
        "spread",
        [*overrides, "algo.group_fit_weighting=spread", "experiment.total_frames=60"],
    )
    stored = spread.algo.replay[:]
    advantage = stored["advantage"].reshape(-1, 5)
    best = (advantage == advantage.max(-1, keepdim=True).values).float()
    gap = advantage.max(-1, keepdim=True).values - advantage.min(-1, keepdim=True).values
    torch.testing.assert_close(
        stored["distill_weight"].reshape(-1, 5), gap * best / best.sum(-1, keepdim=True)
    )
    # Its replay holds targets: a resume without distillation is refused when it loads.
    resume = f"resume={tmp_path / 'distill' / 'last.pt'}"
    plain = compose_config([*TINY, *REPLAY, resume, "algo.group_fit_coeff=0.0"])
    with pytest.raises(ValueError, match="stored with distillation targets.*group_fit_coeff=0.0"):
        Trainer(plain, run_dir=tmp_path / "plain")
