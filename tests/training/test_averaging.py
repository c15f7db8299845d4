"""The averaged policy (``optim.ema_decay``): its arithmetic, checkpoints and resume."""

from __future__ import annotations

import pytest
import torch
from train_setup import TINY, compose_config

from torchrl_grpo.training import Trainer, load_checkpoint
from torchrl_grpo.training import hooks as hooks_module
from torchrl_grpo.training.averaging import PolicyAverage


def test_the_average_is_the_mean_then_fades_by_the_decay():
    net = torch.nn.Linear(3, 2)
    average = PolicyAverage(net, decay=0.75)  # the exact mean up to 1 / (1 - 0.75) = 4
    seen = []
    for _ in range(4):
        torch.nn.init.normal_(net.weight)
        seen.append(net.weight.detach().clone())
        average.update()
        torch.testing.assert_close(average.module.weight, torch.stack(seen).mean(0))
    mean4 = torch.stack(seen).mean(0)
    torch.nn.init.normal_(net.weight)
    average.update()
    torch.testing.assert_close(average.module.weight, 0.75 * mean4 + 0.25 * net.weight.detach())
    assert average.count == 5 and not average.module.weight.requires_grad
    assert net.weight.requires_grad  # the live policy is untouched


def test_buffers_are_copied_and_a_bad_decay_is_refused():
    net = torch.nn.BatchNorm1d(2)
    average = PolicyAverage(net, decay=0.9)
    net.running_mean.fill_(3.0)
    average.update()
    average.update()
    assert torch.equal(average.module.running_mean, torch.full((2,), 3.0))
    for bad in (1.0, -0.1):
        with pytest.raises(ValueError, match=r"optim.ema_decay must be in \[0, 1\)"):
            PolicyAverage(net, decay=bad)


def _train(tmp_path, name, overrides):
    trainer = Trainer(compose_config([*TINY, *overrides]), run_dir=tmp_path / name)
    trainer.train()
    return trainer


@pytest.mark.slow  # 9 s: three runs
def test_runs_evaluate_and_save_the_average_and_resume_exactly(tmp_path, monkeypatch):
    driven = []
    evaluate = hooks_module.evaluate

    def spy(env, policy, **kwargs):
        driven.append(policy)
        return evaluate(env, policy, **kwargs)

    monkeypatch.setattr(hooks_module, "evaluate", spy)
    common = [
        "algo=ppo",
        "rollout.frames_per_batch=32",
        "optim.ema_decay=0.5",
        "experiment.checkpoint_every=1",
    ]
    straight = _train(
        tmp_path,
        "straight",
        [*common, "experiment.total_frames=128", "experiment.final_eval_episodes=1"],
    )
    assert driven and all(policy is straight.average.module for policy in driven)
    ckpt = load_checkpoint(tmp_path / "straight" / "last.pt")
    live, averaged = straight.policy.state_dict(), straight.average.module.state_dict()
    assert any(not torch.equal(live[k], averaged[k]) for k in live)  # the check can fail
    for key in live:
        assert torch.equal(ckpt["policy"][key], averaged[key]), key
        assert torch.equal(ckpt["policy_average"]["train_policy"][key], live[key]), key
    assert ckpt["policy_average"]["count"] == straight.iteration == 4

    stopped = _train(tmp_path, "stopped", [*common, "experiment.total_frames=64"])
    resume = f"resume={tmp_path / 'stopped' / 'last.pt'}"
    resumed = _train(tmp_path, "resumed", [*common, "experiment.total_frames=128", resume])
    assert resumed.average.count == straight.average.count
    for name in ("policy", "eval_policy"):
        a = getattr(straight, name).state_dict()
        b = getattr(resumed, name).state_dict()
        for key in a:
            assert torch.equal(a[key], b[key]), (name, key)
    assert stopped.average.count == 2
