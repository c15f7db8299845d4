"""plot_group: a PNG and a (3, H, W) uint8 image of one group."""

from __future__ import annotations

import torch
from branching_helpers import ScheduledPolicy, actions, plain_env
from torchrl.record.loggers import CSVLogger

from torchrl_grpo.branching import branch_rollout, plot_group, reset_roots


def test_plot_group_writes_png_and_returns_image(tmp_path):
    scenario = "highway-fast-v0"
    roots = reset_roots(plain_env(scenario, seed=0), 2)
    table = actions(scenario, ["IDLE"] * 3, ["LANE_LEFT", "IDLE", "IDLE"], ["FASTER"] * 3)
    data = branch_rollout(plain_env(scenario), ScheduledPolicy(table), roots, 3, 3)
    fig = plot_group(data, 1, path=tmp_path / "group.png", selected=2)
    assert fig.path == tmp_path / "group.png"
    assert fig.path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = fig.image
    assert image.dtype == torch.uint8 and image.dim() == 3 and image.shape[0] == 3
    assert image.shape[1] > 100 and image.shape[2] > 100
    # Not blank: several colours, not a single flat background.
    assert image.float().std() > 10
    assert torch.unique(image.reshape(3, -1), dim=1).shape[1] > 50


def test_plot_group_without_path_draws_different_groups():
    scenario = "merge-v0"
    roots = reset_roots(plain_env(scenario, seed=0), 2)
    data = branch_rollout(plain_env(scenario), ScheduledPolicy(torch.ones(2, 2)), roots, 2, 2)
    a, b = plot_group(data, 0), plot_group(data, 1)
    assert a.path is None
    assert a.image.shape == b.image.shape and not torch.equal(a.image, b.image)


def test_plot_group_video_goes_to_a_torchrl_logger(tmp_path):
    roots = reset_roots(plain_env("merge-v0", seed=0), 1)
    data = branch_rollout(plain_env("merge-v0"), ScheduledPolicy(torch.ones(2, 2)), roots, 2, 2)
    fig = plot_group(data)
    logger = CSVLogger("run", log_dir=str(tmp_path), video_format="pt")
    logger.log_video("branch_group", fig.video)
    saved = list((tmp_path / "run" / "videos").iterdir())
    assert len(saved) == 1 and torch.equal(torch.load(saved[0])[0, 0], fig.image)
