"""A resumed run remembers: its checkpoint's config, its env; bad files are named."""

from __future__ import annotations

import logging

import pytest
import torch
from train_setup import TINY, compose_config

from torchrl_grpo.training import Hook, Trainer, load_checkpoint

# Away from today's defaults: what a resume must take from the checkpoint, not conf/.
_RUN = [
    *TINY,
    "algo.group_size=2",
    "rollout.decision_interval=2",
    "algo.epochs=2",
    "experiment.total_frames=110",
    "experiment.checkpoint_every=1",
]


class _StopAt(Hook):
    """Asks the loop to stop after ``iteration`` iterations, as a Ctrl-C does."""

    def __init__(self, iteration: int) -> None:
        self.iteration = iteration

    def due(self, trainer, batch):
        return trainer.progress.iteration == self.iteration

    def on_iteration(self, trainer, batch, result):
        trainer.stop_requested = True
        return {}


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """A run stopped after 2 iterations: its checkpoint, and the run that was not stopped."""
    root = tmp_path_factory.mktemp("resume")
    straight = Trainer(compose_config(_RUN), run_dir=root / "straight")
    straight.train()
    stopped = Trainer(compose_config(_RUN), run_dir=root / "stopped", hooks=[_StopAt(2)])
    assert stopped.train().interrupted
    assert 0 < stopped.frames < straight.frames
    return root / "stopped" / "last.pt", straight


def test_a_resume_without_overrides_continues_exactly(stopped, tmp_path):
    path, straight = stopped
    cfg = compose_config([f"resume={path}"])
    # The checkpoint's config, not today's defaults.
    assert (cfg.algo.group_size, cfg.rollout.decision_interval, cfg.algo.epochs) == (2, 2, 2)
    assert compose_config([]).algo.group_size != 2
    resumed = Trainer(cfg, run_dir=tmp_path / "resumed")
    resumed.train()
    assert (resumed.iteration, resumed.frames) == (straight.iteration, straight.frames)
    a, b = straight.algo.loss.state_dict(), resumed.algo.loss.state_dict()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_an_override_applies_on_top_and_is_logged(stopped, caplog):
    path, _ = stopped
    with caplog.at_level(logging.WARNING, logger="torchrl_grpo"):
        cfg = compose_config([f"resume={path}", "algo.epochs=3"])
    assert (cfg.algo.epochs, cfg.algo.group_size) == (3, 2)
    assert f"resume={path}: algo.epochs=3 (the checkpoint's run had 2)" in caplog.text
    assert "group_size" not in caplog.text


def test_an_override_to_todays_default_still_applies(stopped, caplog):
    path, _ = stopped
    default = compose_config([]).algo.group_size
    with caplog.at_level(logging.WARNING, logger="torchrl_grpo"):
        cfg = compose_config([f"resume={path}", f"algo.group_size={default}"])
    assert cfg.algo.group_size == default != 2
    assert f"algo.group_size={default} (the checkpoint's run had 2)" in caplog.text


def test_another_env_is_refused_at_load_naming_the_env(stopped):
    path, _ = stopped
    with pytest.raises(ValueError, match="env.scenario='highway-fast-v0', not 'merge-v0'"):
        compose_config([f"resume={path}", "env=merge"])
    with pytest.raises(ValueError, match="env.config"):
        compose_config([f"resume={path}", "+env.config.lanes_count=2"])


def test_a_truncated_file_or_another_file_is_not_a_valid_checkpoint(stopped, tmp_path):
    path, _ = stopped
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    text = tmp_path / "notes.pt"
    text.write_text("not a checkpoint")
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    for bad in (truncated, text, empty):
        with pytest.raises(ValueError, match=f"not a valid checkpoint: {bad}"):
            load_checkpoint(bad)
        with pytest.raises(ValueError, match=f"not a valid checkpoint: {bad}"):
            compose_config([f"resume={bad}"])
    # A tensor saved by torch is a file torch reads, not a checkpoint.
    tensor = tmp_path / "tensor.pt"
    torch.save(torch.zeros(2), tensor)
    with pytest.raises(ValueError, match=f"not a valid checkpoint: {tensor}"):
        load_checkpoint(tensor)


def test_a_resume_under_another_thread_count_warns_and_trains_on(stopped, tmp_path, caplog):
    path, straight = stopped
    saved = load_checkpoint(path)["threads"]
    assert saved == torch.get_num_threads()
    cfg = compose_config([f"resume={path}"])
    with caplog.at_level(logging.WARNING, logger="torchrl_grpo"):
        Trainer(cfg, run_dir=tmp_path / "same")
    assert "torch threads" not in caplog.text  # the same count: nothing to say
    before = torch.get_num_threads()
    torch.set_num_threads(saved + 1)
    try:
        with caplog.at_level(logging.WARNING, logger="torchrl_grpo"):
            resumed = Trainer(cfg, run_dir=tmp_path / "more")
        assert (
            f"{path} was trained with {saved} torch threads and resumes with {saved + 1}: "
            f"it will not continue bit for bit (OMP_NUM_THREADS={saved}" in caplog.text
        )
        resumed.train()  # a warning, not a refusal: the run goes on to its end
    finally:
        torch.set_num_threads(before)
    assert (resumed.iteration, resumed.frames) == (straight.iteration, straight.frames)
