"""NeighbourFeatures / NeighbourMLP: every nearby lane's neighbours, checked by hand."""

import torch
from modules_helpers import LAYOUT, scene
from omegaconf import OmegaConf

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import KinematicsLayout, RandomPolicy
from torchrl_grpo.modules.neighbour_features import NeighbourFeatures, NeighbourMLP
from torchrl_grpo.training.group_schemas import MLPModelConfig
from torchrl_grpo.training.model_builder import make_policy


def test_features_of_a_scene_computed_by_hand():
    # Ego in the middle lane at 30 m/s. Left lane: cars 40 m and 70 m ahead, 10 and 5 m/s
    # slower. Own lane: a car 10 m behind, 4 m/s faster. Right lane: a car 60 m ahead.
    others = [(40.0, -1, -10.0), (70.0, -1, -5.0), (-10.0, 0, 4.0), (60.0, 1, 0.0)]
    f = NeighbourFeatures(LAYOUT)(scene(1, 30.0, others))
    expected = [
        1.0,  # (30 - 25) / 5
        0.0,  # in the middle of its lane
        0.0,  # not changing lane
        # left: exists; leader gap 35 / 50, closing 10 / 10; second gap 65 / 50, closing
        # 5 / 10; nobody behind (100 m / 50, 0); 1 / ttc = 10 / 35 ahead, 0 behind
        1.0, 0.7, 1.0, 1.3, 0.5, 2.0, 0.0, 10 / 35, 0.0,
        # own lane: no leader (2, 0) nor second (2, 0); a follower 5 m behind closing at
        # 4 m/s (5 / 50, 0.4), 1 / ttc 4 / 5
        1.0, 2.0, 0.0, 2.0, 0.0, 0.1, 0.4, 0.0, 0.8,
        # right: exists; leader 55 m ahead at our speed; nothing else
        1.0, 1.1, 0.0, 2.0, 0.0, 2.0, 0.0, 0.0, 0.0,
    ]  # fmt: skip
    torch.testing.assert_close(f, torch.tensor(expected))


def test_a_missing_lane_and_an_offset_in_the_lane():
    cols = {k: torch.zeros(5) for k in LAYOUT.features}
    cols["presence"][0], cols["y"][0], cols["vx"][0] = 1.0, 1.0, 20.0  # 1 m right of lane 0
    f = NeighbourFeatures(LAYOUT)(LAYOUT.encode(cols))
    assert f[3].item() == 0.0  # no lane to the left of lane 0
    torch.testing.assert_close(f[1], torch.tensor(0.5))  # 1 m / 2
    torch.testing.assert_close(f[0], torch.tensor(-1.0))  # (20 - 25) / 5


def test_features_ignore_the_order_of_the_other_vehicles():
    config = {"observation": {"type": "Kinematics", "vehicles_count": 8, "see_behind": True}}
    env = HighwayEnv("highway-fast-v0", config=config, seed=0)
    obs = env.rollout(60, RandomPolicy(5, seed=0), break_when_any_done=False)["observation"]
    perm = torch.tensor([0, 3, 1, 7, 4, 2, 6, 5])
    features = NeighbourFeatures(KinematicsLayout.from_highway_config(env.config))
    assert torch.equal(features(obs), features(obs[:, perm]))


def test_neighbour_mlp_shapes_and_the_config_builds_it():
    assert NeighbourMLP(LAYOUT, 5, num_cells=(8,))(torch.zeros(2, 3, 5, 5)).shape == (2, 3, 5)
    cfg = OmegaConf.structured(MLPModelConfig(kind="neighbours", num_cells=[16]))
    actor = make_policy(cfg, HighwayEnv("highway-fast-v0", seed=0))
    assert isinstance(actor.module[0].module, NeighbourMLP)
