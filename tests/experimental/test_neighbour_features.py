"""The experimental neighbours network (``model=lab model.kind=neighbours``): its features
checked by hand, the kind registered with the core, and old configs of it read as lab runs."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "modules"))

from modules_helpers import LAYOUT, scene  # noqa: E402

from torchrl_grpo.envs import HighwayEnv  # noqa: E402
from torchrl_grpo.experimental.grpo_lab import GRPOLabModelConfig  # noqa: E402
from torchrl_grpo.experimental.neighbour_features import (  # noqa: E402
    NeighbourFeatures,
    NeighbourMLP,
)
from torchrl_grpo.modules import KinematicsLayout, RandomPolicy  # noqa: E402
from torchrl_grpo.training import compose_config  # noqa: E402
from torchrl_grpo.training.algos.grpo_config import FIXED_SETTINGS  # noqa: E402
from torchrl_grpo.training.config import to_container, typed_config  # noqa: E402
from torchrl_grpo.training.model_builder import make_policy  # noqa: E402

pytestmark = pytest.mark.experimental
ROOT = Path(__file__).resolve().parents[2]


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


def test_neighbour_mlp_shapes_and_the_lab_config_builds_it():
    assert NeighbourMLP(LAYOUT, 5, num_cells=(8,))(torch.zeros(2, 3, 5, 5)).shape == (2, 3, 5)
    cfg = OmegaConf.structured(GRPOLabModelConfig(kind="neighbours", num_cells=[16]))
    actor = make_policy(cfg, HighwayEnv("highway-fast-v0", seed=0))
    assert isinstance(actor.module[0].module, NeighbourMLP)
    lab_run = ["experiment=smoke", "algo=grpo_lab", "model=lab", "model.kind=neighbours"]
    lab = compose_config(lab_run)
    assert lab.model.kind == "neighbours" and list(lab.model.num_cells) == [32]


def test_the_cores_model_kinds_do_not_list_it():
    with pytest.raises(ConfigCompositionException) as info:
        compose_config(["model=mlp", "model.kind=neighbours"])
    assert "model.kind" in str(info.value.__cause__)
    with pytest.raises(ConfigCompositionException, match="model/neighbours"):
        compose_config(["model=neighbours"])


def _neighbours_run(*overrides: str) -> dict:
    """The config a ``model=neighbours`` run of today's core wrote before the kind moved."""
    cfg = to_container(compose_config(["experiment=smoke", *overrides]))
    cfg["model"]["kind"] = "neighbours"
    return cfg


def test_an_old_neighbours_run_reads_as_a_lab_run_with_its_recipes_settings():
    old = _neighbours_run()  # grpo_branch, whose fixed settings the saved config lacks
    lab = typed_config(old)
    assert str(lab.algo.name) == "grpo_lab" and lab.model.kind == "neighbours"
    assert OmegaConf.get_type(lab.model) is GRPOLabModelConfig
    fixed = FIXED_SETTINGS["grpo_branch"]
    for group in ("algo", "rollout"):
        for key, value in fixed.get(group, {}).items():
            assert lab[group][key] == value, f"{group}.{key}"
    for key, value in old["algo"].items():
        if key != "name":
            assert lab.algo[key] == value, key
    # The same network, weight for weight, as the old config's model builds.
    env = HighwayEnv("highway-fast-v0", seed=0)
    torch.manual_seed(0)
    before = make_policy(OmegaConf.create(old["model"]), env).state_dict()
    torch.manual_seed(0)
    after = make_policy(lab.model, env).state_dict()
    assert before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_an_old_neighbours_run_of_ppo_is_refused_naming_the_lab():
    with pytest.raises(ValueError, match=r"model.kind='neighbours'.*algo=grpo_lab"):
        typed_config(_neighbours_run("algo=ppo"))


def test_without_the_lab_an_old_neighbours_run_is_refused_naming_the_package():
    # A fresh interpreter without torchrl_grpo.experimental imported.
    code = (
        "from torchrl_grpo.training.config import typed_config\n"
        "typed_config({'algo': {'name': 'grpo_branch'}, 'model': {'kind': 'neighbours'}})"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 1
    assert "model.kind='neighbours' is not a network kind of the core" in proc.stderr
    assert "import torchrl_grpo.experimental" in proc.stderr and "algo=grpo_lab" in proc.stderr
