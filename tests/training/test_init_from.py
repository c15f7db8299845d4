"""A new run started from a trained run's saved policy (``init_from``)."""

from __future__ import annotations

import shutil

import pytest
import torch
from tensordict import TensorDict
from train_setup import TINY, compose_config

from torchrl_grpo.training import Trainer, load_checkpoint, make_env, make_policy
from torchrl_grpo.training.checkpoint import save_checkpoint
from torchrl_grpo.training.config import to_container

TENSOR = ["env.backend=tensor", "env.num_envs=32"]
CRASH_HEAD = ["model.crash_head=true", "model.crash_aversion=3"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny GRPO run with a crash head: the checkpoint new runs start from."""
    root = tmp_path_factory.mktemp("trained")
    cfg = compose_config([*TINY, *TENSOR, *CRASH_HEAD, "experiment.total_frames=60"])
    Trainer(cfg, run_dir=root).train()
    return root / "last.pt"


def assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


@pytest.mark.slow  # the default suite's 10-minute budget
def test_a_run_starts_from_the_saved_policy_and_so_do_its_reference_and_average(trained, tmp_path):
    saved = load_checkpoint(trained)["policy"]
    # Another crash aversion weighs the same parameters: it is not refused.
    common = [*TINY, *TENSOR, *CRASH_HEAD[:1], "model.crash_aversion=5"]
    common += ["algo.kl_to_ref_coeff=0.04", "optim.ema_decay=0.9", "seed=3"]
    fresh = Trainer(compose_config(common), run_dir=tmp_path / "fresh")
    assert any(not torch.equal(saved[k], v) for k, v in fresh.policy.state_dict().items())

    cfg = compose_config([*common, f"init_from={trained}", "experiment.total_frames=100"])
    trainer = Trainer(cfg, run_dir=tmp_path / "init")
    assert_same_weights(trainer.policy.state_dict(), saved)
    assert_same_weights(trainer.average.module.state_dict(), saved)
    reference = trainer.algo.loss.target_actor_network_params
    assert (reference.data == TensorDict.from_module(trainer.policy).data).all()
    result = trainer.train()  # and it trains on from there
    assert result.frames >= 100
    assert any(not torch.equal(saved[k], v) for k, v in trainer.policy.state_dict().items())


def test_weights_of_another_network_or_env_and_a_missing_file_are_refused(trained, tmp_path):
    mlp_cfg = compose_config([*TINY, *TENSOR, "model=mlp"])
    mlp = make_policy(mlp_cfg.model, make_env(mlp_cfg.env))
    mlp_path = save_checkpoint(
        {"config": to_container(mlp_cfg), "policy": mlp.state_dict()}, tmp_path / "mlp.pt"
    )
    with pytest.raises(ValueError, match=r"does not fit .*model.kind='mlp', not 'scene'"):
        Trainer(compose_config([*TINY, *TENSOR, f"init_from={mlp_path}"]), run_dir=tmp_path)
    with pytest.raises(ValueError, match=r"model.crash_head=True, not False"):
        no_head = [*TINY, *TENSOR, "model.crash_head=false", f"init_from={trained}"]
        Trainer(compose_config(no_head), run_dir=tmp_path)
    # Same parameters, another prior: refused as a resume refuses it.
    lab = ["algo=grpo_lab", "model=lab"]  # a prior is a setting of the experimental algo
    prior = [*TINY, *TENSOR, *CRASH_HEAD, *lab, "model.prior=rule", f"init_from={trained}"]
    with pytest.raises(ValueError, match=r"model.prior=None, not 'rule'"):
        Trainer(compose_config(prior), run_dir=tmp_path)

    ckpt = load_checkpoint(trained)
    ckpt["config"]["env"]["config"] = {"lanes_count": 3}
    other = save_checkpoint(ckpt, tmp_path / "other.pt")
    with pytest.raises(ValueError, match=r"init_from=.*other.pt was trained on .*lanes_count"):
        Trainer(compose_config([*TINY, *TENSOR, *CRASH_HEAD, f"init_from={other}"]), tmp_path)

    missing = tmp_path / "nowhere" / "last.pt"
    with pytest.raises(FileNotFoundError, match="nowhere"):
        Trainer(compose_config([*TINY, *TENSOR, *CRASH_HEAD, f"init_from={missing}"]), tmp_path)


@pytest.mark.slow  # the default suite's 10-minute budget
def test_a_resumed_run_continues_from_its_own_weights_without_the_init_file(trained, tmp_path):
    start = tmp_path / "start.pt"
    shutil.copy(trained, start)
    common = [*TINY, *TENSOR, *CRASH_HEAD, f"init_from={start}", "experiment.checkpoint_every=1"]

    def train(name, frames):
        trainer = Trainer(
            compose_config([*common, f"experiment.total_frames={frames}"]), tmp_path / name
        )
        trainer.train()
        return trainer

    straight = train("straight", 700)
    stopped = train("stopped", 300)
    start.unlink()  # the resume must not read it: its own checkpoint holds the weights
    cfg = compose_config(
        [f"resume={tmp_path / 'stopped' / 'last.pt'}", "experiment.total_frames=700"]
    )
    resumed = Trainer(cfg, run_dir=tmp_path / "resumed")
    resumed.train()
    assert (resumed.iteration, resumed.frames) == (straight.iteration, straight.frames)
    assert stopped.iteration < straight.iteration
    assert_same_weights(resumed.policy.state_dict(), straight.policy.state_dict())
    final, before = straight.policy.state_dict(), stopped.policy.state_dict()
    assert any(not torch.equal(final[k], before[k]) for k in final)  # the control can fail
