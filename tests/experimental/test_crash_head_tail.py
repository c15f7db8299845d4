"""The experimental crash head scored under the base tail alone
(``algo=grpo_lab algo.crash_head_tail=true``): its checks, its split of each group, and
the labels and replay of a tiny run."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))

from train_helpers import REPLAY, train_run  # noqa: E402
from train_setup import TINY, compose_config  # noqa: E402

from torchrl_grpo.branching.keys import MASK  # noqa: E402
from torchrl_grpo.experimental.crash_head_tail import base_tail_crashes  # noqa: E402
from torchrl_grpo.experimental.grpo_lab import GRPOLab  # noqa: E402
from torchrl_grpo.training import Trainer  # noqa: E402
from torchrl_grpo.training.algos.enumerated import branch_crashed  # noqa: E402
from torchrl_grpo.training.config_checks import check_config  # noqa: E402

pytestmark = pytest.mark.experimental

N_ACTIONS = 5
# The learner's own step after the first action, then always-SLOWER; the head's half
# brakes right after it.
TWO_TAILS = [
    *REPLAY,
    "algo.tail_learner_steps=1",
    f"algo.group_size={2 * N_ACTIONS}",
    "algo.crash_head_tail=true",
    "model.crash_head=true",
]


def test_the_labels_are_the_second_halfs_crashes_by_root_and_action():
    # Root 0: action 1 crashes after the learner, action 0 after the base tail only.
    terminated = torch.zeros(2, 4, 3, 1, dtype=torch.bool)
    terminated[0, 1, 2] = True
    terminated[0, 2, 1] = True
    mask = torch.ones(2, 4, 3, dtype=torch.bool)
    mask[0, 2, 2] = False  # the crashed branch ends there
    batch = TensorDict(
        {
            MASK: mask,
            ("next", "terminated"): terminated,
            "branch": torch.arange(4).expand(2, 3, 4).transpose(1, 2),
        },
        batch_size=[2, 4, 3],
    )
    learner, labels = base_tail_crashes(batch)
    assert learner["branch"][..., 0].tolist() == [[0, 1], [0, 1]]
    assert labels[..., 0].tolist() == [[True, False], [False, False]]
    assert (labels == labels[..., :1]).all()  # on every step of the branch
    with pytest.raises(ValueError, match="even size, got 3"):
        base_tail_crashes(batch[:, :3])


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("model.crash_head=false", "set model.crash_head=true"),
        ("algo.tail_learner_steps=0", r"algo.tail_learner_steps >= 1 \(got slower and 0\)"),
        ("algo.crash_label=bootstrap", "set algo.crash_label=branch"),
        ("algo.first_action=sample", "set algo.first_action=enumerate"),
    ],
)
def test_settings_that_cannot_pair_the_halves_are_refused(override, message):
    cfg = compose_config([*TINY, *TWO_TAILS, override])
    with pytest.raises(ValueError, match=message):
        check_config(cfg)


def test_a_group_size_other_than_twice_the_actions_is_refused(tmp_path):
    cfg = compose_config([*TINY, *TWO_TAILS, "algo.group_size=5"])
    check_config(cfg)  # the actions are the env's: known once it is built
    with pytest.raises(ValueError, match="set algo.group_size=10, twice the 5 actions"):
        Trainer(cfg, run_dir=tmp_path / "refused")


@pytest.mark.slow  # 14 s of training: the default suite's 10-minute budget
def test_the_head_learns_the_base_tails_crashes_and_the_policy_its_own_half(tmp_path, monkeypatch):
    seen = []
    update, targets = GRPOLab.update, GRPOLab.crash_targets

    def spy_update(self, batch, timer):
        seen.append({"batch": batch.clone()})
        return update(self, batch, timer)

    def spy_targets(self, batch):
        labels = targets(self, batch)
        seen[-1].update(trained=batch.batch_size, labels=labels.clone())
        return labels

    monkeypatch.setattr(GRPOLab, "update", spy_update)
    monkeypatch.setattr(GRPOLab, "crash_targets", spy_targets)
    trainer = train_run(tmp_path, "two_tails", [*TWO_TAILS, "experiment.total_frames=200"])
    assert len(seen) >= 2
    for step in seen:
        full = step["batch"]
        assert full.batch_size[1] == 2 * N_ACTIONS
        assert step["trained"][1] == N_ACTIONS  # the policy's groups: the learner's half
        expected = branch_crashed(full[:, N_ACTIONS:], MASK)
        assert torch.equal(step["labels"], expected)
        # The halves take the same first actions from the same roots.
        actions = full["action"][:, :, 0]
        assert torch.equal(actions[:, :N_ACTIONS], actions[:, N_ACTIONS:])
    # The replay holds 50 groups of the learner's half: 5 rows each, not 10.
    assert trainer.algo.replay.storage.max_size == 50 * N_ACTIONS


def test_a_run_resumes_with_its_half_sized_replay(tmp_path):
    stopped = train_run(tmp_path, "stopped", [*TWO_TAILS, "experiment.total_frames=100"])
    rows = len(stopped.algo.replay)
    assert 0 < rows <= 50 * N_ACTIONS
    cfg = compose_config(
        [*TINY, *TWO_TAILS, "experiment.total_frames=200", f"resume={tmp_path / 'stopped/last.pt'}"]
    )
    resumed = Trainer(cfg, run_dir=tmp_path / "resumed")
    assert len(resumed.algo.replay) == rows
    assert resumed.algo.replay.storage.max_size == 50 * N_ACTIONS
