"""Without Ray: the library imports, and asking for the Ray backend names the extra."""

from __future__ import annotations

import sys

import pytest
from distributed_helpers import ENV_FACTORY, make_policy
from omegaconf import OmegaConf

from torchrl_grpo.distributed import RayGroupCollector
from torchrl_grpo.distributed.ray_setup import RAY_EXTRA_HINT, require_ray
from torchrl_grpo.training.collect import make_collector
from torchrl_grpo.training.config import Config, GRPOConfig, PPOConfig, check_config
from torchrl_grpo.training.group_schemas import RayRolloutConfig


@pytest.fixture
def no_ray(monkeypatch):
    # A None entry in sys.modules makes `import ray` raise ImportError.
    monkeypatch.setitem(sys.modules, "ray", None)


def test_require_ray_names_the_extra(no_ray):
    with pytest.raises(ImportError, match=r'pip install "torchrl_grpo\[ray\]"'):
        require_ray()


def test_collector_without_ray_names_the_extra(no_ray):
    with pytest.raises(ImportError) as err:
        RayGroupCollector(ENV_FACTORY, make_policy(), group_size=2, horizon=2, groups_per_batch=1)
    assert str(err.value) == RAY_EXTRA_HINT


def test_training_config_without_ray_names_the_extra(no_ray):
    cfg = OmegaConf.create(
        {
            "algo": {"name": "grpo_branch", "group_size": 2, "roots": "reset", "select": "best"},
            "env": {"scenario": "merge-v0", "config": {}},
            "rollout": {
                "horizon": 2,
                "groups_per_batch": 2,
                "decision_interval": 2,
                "ray": {"num_actors": 1},
            },
        }
    )
    with pytest.raises(ImportError, match=r"torchrl_grpo\[ray\]"):
        make_collector(cfg, None, make_policy(), seed=0)


def test_config_checks_the_ray_keys():
    def cfg(algo, **ray):
        rollout = RayRolloutConfig(groups_per_batch=2)
        for key, value in ray.items():
            setattr(rollout.ray, key, value)
        return OmegaConf.structured(Config(algo=algo, rollout=rollout))

    check_config(cfg(GRPOConfig(name="grpo_branch")))
    with pytest.raises(ValueError, match="not GRPO"):
        check_config(cfg(PPOConfig(name="ppo")))
    with pytest.raises(ValueError, match="num_actors"):
        check_config(cfg(GRPOConfig(name="grpo_branch"), num_actors=3))
    config = cfg(GRPOConfig(name="grpo_branch"))
    config.rollout.num_workers = 2  # two workers per actor, each actor in one process
    with pytest.raises(ValueError, match=r"num_workers \(workers per Ray actor\) must be 1"):
        check_config(config)
    config.rollout.backend = "serial"
    check_config(config)
    config.rollout.backend = "ray"  # the former spelling of rollout=ray
    with pytest.raises(ValueError, match="rollout.backend=ray: choose rollout=ray"):
        check_config(config)
