"""The algorithm registry: a new algorithm is one class and one YAML file, and it trains."""

from __future__ import annotations

import shutil
from dataclasses import dataclass

import pytest
import torch
from omegaconf import OmegaConf
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value.functional import reward2go
from train_setup import CONF, TINY, compose_config

from torchrl_grpo.training import (
    GRPO,
    PPO,
    AlgoConfig,
    Algorithm,
    TeacherDistill,
    Trainer,
    load_checkpoint,
    register_algorithm,
    register_configs,
)
from torchrl_grpo.training.algos.registry import ALGORITHMS, algorithm_for
from torchrl_grpo.training.algos.search_distill import SearchDistill


@dataclass
class PGConfig(AlgoConfig):
    """``algo=pg``: a critic-free policy gradient on normalised rewards-to-go."""

    name: str = "pg"
    gamma: float = 0.9
    clip_epsilon: float = 0.2


@register_algorithm
class PG(Algorithm):
    """The docs' worked example (docs/training.md), with a count of its updates."""

    names = ("pg",)
    config_class = PGConfig
    config_name = "base_pg"

    @classmethod
    def make_loss(cls, algo_cfg, policy, value=None):
        return ClipPPOLoss(
            policy,
            None,
            critic_coeff=None,
            clip_epsilon=algo_cfg.clip_epsilon,
            entropy_coeff=algo_cfg.entropy_coeff,
        )

    def update(self, batch, timer):
        with timer("advantage"):
            data = batch.exclude("state", ("next", "state"))
            done = data["next", "done"]
            returns = reward2go(data["next", "reward"], done, self.cfg.algo.gamma, time_dim=-2)
            data["advantage"] = (returns - returns.mean()) / (returns.std() + 1e-6)
        self.batches = getattr(self, "batches", 0) + 1
        with timer("update"):
            return self.optimise(data.reshape(-1))


YAML = """\
defaults:
  - base_pg
  - _self_
name: pg
gamma: 0.9
epochs: 2
minibatch_size: 32
"""


@pytest.fixture
def conf_with_pg(tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(CONF, conf)
    (conf / "algo" / "pg.yaml").write_text(YAML)
    return conf


def test_a_registered_algorithm_trains_from_its_yaml(tmp_path, conf_with_pg):
    assert "base_pg.yaml" in register_configs().list("algo")
    # experiment=smoke sets algo.epochs and algo.minibatch_size: set them after it.
    overrides = [*TINY, "algo=pg", "rollout=ppo", "rollout.frames_per_batch=32"]
    overrides += ["algo.epochs=2", "algo.minibatch_size=32"]
    cfg = compose_config([*overrides, "experiment.total_frames=64"], conf=conf_with_pg)
    assert OmegaConf.get_type(cfg.algo) is PGConfig and algorithm_for(cfg.algo) is PG
    trainer = Trainer(cfg, run_dir=tmp_path / "pg")
    start = {k: v.clone() for k, v in trainer.policy.state_dict().items()}
    result = trainer.train()
    assert isinstance(trainer.algo, PG) and trainer.algo.batches == result.iterations == 2
    assert trainer.algo.updates == 2 * 2  # 2 epochs of one minibatch of 32 per batch
    ckpt = load_checkpoint(result.checkpoint)
    assert ckpt["config"]["algo"]["name"] == "pg" and ckpt["updates"] == 4
    assert any(not torch.equal(v, ckpt["policy"][k]) for k, v in start.items())
    # It resumes like the built-in ones: exactly where it stopped.
    resumed = Trainer(
        compose_config(
            [*overrides, "experiment.total_frames=96", f"resume={result.checkpoint}"],
            conf=conf_with_pg,
        ),
        run_dir=tmp_path / "resumed",
    )
    assert (resumed.iteration, resumed.algo.updates) == (2, 4)
    assert resumed.train().iterations == 3


def test_the_registry_names_every_built_in_algorithm():
    # grpo_lab: the experimental package's, registered when it is imported (conftest).
    built_in = {name: cls for name, cls in ALGORITHMS.items() if name not in ("pg", "grpo_lab")}
    assert built_in == {
        "grpo_branch": GRPO,
        "grpo_episode": GRPO,
        "ppo": PPO,
        "distill": TeacherDistill,
        "search_distill": SearchDistill,
    }
    # By name, or by schema when the name is not set yet.
    assert algorithm_for(OmegaConf.create({"name": "grpo_episode"})) is GRPO
    assert algorithm_for(OmegaConf.structured(PGConfig(name="???"))) is PG
    with pytest.raises(ValueError, match="algo.name='sac' is not a registered algorithm"):
        algorithm_for(OmegaConf.create({"name": "sac"}))


def test_a_taken_name_or_a_nameless_algorithm_is_refused():
    class OtherPPO(PPO):
        names = ("ppo",)

    with pytest.raises(ValueError, match="algo.name='ppo' is taken by"):
        register_algorithm(OtherPPO)

    class Nameless(Algorithm):
        pass

    with pytest.raises(ValueError, match="needs names and a config_name"):
        register_algorithm(Nameless)
    assert ALGORITHMS["ppo"] is PPO
    register_algorithm(PPO)  # the same class again: a no-op
