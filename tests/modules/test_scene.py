"""SceneFeatures / SceneMLP: driving features of a Kinematics table, checked by hand."""

import pytest
import torch
from modules_helpers import LAYOUT, scene
from omegaconf import OmegaConf

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import KinematicsLayout, RandomPolicy, SceneMLP
from torchrl_grpo.modules.scene_features import SceneFeatures
from torchrl_grpo.training.group_schemas import MLPModelConfig
from torchrl_grpo.training.model_builder import make_policy


def test_features_of_a_scene_computed_by_hand():
    # Ego in the middle lane at 30 m/s. Left lane: a car 40 m ahead, 10 m/s slower,
    # and one 10 m behind. Own lane: nothing. Right lane: a car 60 m ahead at our speed.
    obs = scene(1, 30.0, [(40.0, -1, -10.0), (-10.0, -1, 0.0), (60.0, 1, 0.0)])
    f = SceneFeatures(LAYOUT)(obs)
    expected = [
        1.0,  # (30 - 25) / 5
        0.0,  # not changing lane
        # left: exists, gap (40 - 5) / 50, closing 10 / 10, 1 / ttc = 10 / 35
        1.0, 0.7, 1.0, 10 / 35,
        # safe: the leader leaves 35 m >= 3 m + 3 s x 10 m/s, the follower 5 m >= 3 m;
        # a car within 25 m (the one 10 m behind)
        1.0, 1.0,
        # own lane: exists, no leader (100 m / 50), not closing, no collision ahead
        1.0, 2.0, 0.0, 0.0,
        # right: exists, gap 55 / 50, not closing, no collision; safe; nothing within 25 m
        1.0, 1.1, 0.0, 0.0, 1.0, 0.0,
    ]  # fmt: skip
    torch.testing.assert_close(f, torch.tensor(expected))


def test_a_missing_lane_and_an_unsafe_one():
    # Ego in the left lane (no lane further left); a car 2 m behind in the right lane.
    f = SceneFeatures(LAYOUT)(scene(0, 20.0, [(-7.0, 1, 0.0)]))
    assert f[2].item() == 0.0  # the left lane does not exist
    assert f[12].item() == 1.0 and f[16].item() == 0.0  # right lane exists, unsafe
    assert f[17].item() == 1.0  # and occupied within 25 m


def test_features_ignore_the_order_of_the_other_vehicles():
    env = HighwayEnv("highway-fast-v0", seed=0)
    obs = env.rollout(60, RandomPolicy(5, seed=0), break_when_any_done=False)["observation"]
    perm = torch.tensor([0, 3, 1, 4, 2])
    features = SceneFeatures(KinematicsLayout.from_highway_config(env.config))
    assert torch.equal(features(obs), features(obs[:, perm]))


def test_scene_mlp_shapes_and_the_config_builds_it():
    assert SceneMLP(LAYOUT, 5, num_cells=(8,))(torch.zeros(2, 3, 5, 5)).shape == (2, 3, 5)
    cfg = OmegaConf.structured(MLPModelConfig(kind="scene", num_cells=[16]))
    actor = make_policy(cfg, HighwayEnv("highway-fast-v0", seed=0))
    assert isinstance(actor.module[0].module, SceneMLP)


@pytest.mark.parametrize(
    "observation,problem",
    [
        ({"type": "Kinematics", "features": ["presence", "x"]}, "needed but not observed"),
        ({"type": "TimeToCollision"}, "observes something else"),
    ],
)
def test_the_config_refuses_a_scene_it_cannot_read(observation, problem):
    cfg = OmegaConf.structured(MLPModelConfig(kind="scene"))
    env = HighwayEnv("highway-fast-v0", config={"observation": observation}, seed=0)
    with pytest.raises(ValueError, match=f"model.kind=scene.*{problem}"):
        make_policy(cfg, env)


def test_the_speed_feature_is_centred_on_the_envs_target_speeds():
    from omegaconf import OmegaConf

    from torchrl_grpo.envs import HighwayEnv
    from torchrl_grpo.training.group_schemas import MLPModelConfig
    from torchrl_grpo.training.model_builder import make_net

    layout = KinematicsLayout()
    cols = {f: torch.zeros(5) for f in layout.features}
    cols["presence"][0], cols["y"][0], cols["vx"][0] = 1.0, 4.0, 35.0
    observation = layout.encode(cols)
    # Target speeds 30, 35 and 40 m/s: 35 m/s is the middle, 40 m/s one half range up.
    assert SceneFeatures(layout, (30.0, 35.0, 40.0))(observation)[0].item() == 0.0
    assert SceneFeatures(layout)(observation)[0].item() == 2.0  # the default 25 +- 5
    # The trainer's network takes them from the env's config.
    speeds = {"action": {"type": "DiscreteMetaAction", "target_speeds": [30, 35, 40]}}
    cfg = OmegaConf.merge(OmegaConf.structured(MLPModelConfig), {"kind": "scene"})
    net = make_net(cfg, HighwayEnv(config=speeds), 5)
    assert (net.features.speed_centre, net.features.speed_scale) == (35.0, 5.0)
    assert make_net(cfg, HighwayEnv(), 5).features.speed_centre == 25.0
