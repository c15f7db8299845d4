"""The reference policy: frozen by default, synced or mixed by ReferenceSync."""

from __future__ import annotations

import warnings

import pytest
import torch
from objectives_builders import branch_batch, categorical_actor

from torchrl_grpo.objectives import GRPOLoss, ReferenceSync


def flat(params) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in params.values(True, True)])


def train_step(loss: GRPOLoss, optim: torch.optim.Optimizer, td) -> None:
    out = loss(td.clone())
    optim.zero_grad()
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    optim.step()


def setup(beta: float = 0.1):
    actor = categorical_actor()
    td = branch_batch(actor, (2, 3, 4))
    loss = GRPOLoss(actor, kl_to_ref_coeff=beta)
    optim = torch.optim.SGD(loss.parameters(), lr=0.5)
    return loss, optim, td


def test_frozen_reference_does_not_move_and_does_not_warn():
    loss, optim, td = setup()
    start = flat(loss.target_actor_network_params).clone()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "no target updater" warning
        for _ in range(3):
            train_step(loss, optim, td)
    assert torch.equal(flat(loss.target_actor_network_params), start)
    assert not torch.equal(flat(loss.actor_network_params), start)
    assert loss(td.clone())["kl_to_ref"] > 0


def test_hard_sync_every_n_updates():
    loss, optim, td = setup()
    sync = ReferenceSync(loss, ref_model_sync_steps=3, ref_model_mixup_alpha=1.0)
    start = flat(loss.target_actor_network_params).clone()
    for _ in range(2):
        train_step(loss, optim, td)
        sync.step()
        assert torch.equal(flat(loss.target_actor_network_params), start)
    train_step(loss, optim, td)
    sync.step()
    assert torch.equal(flat(loss.target_actor_network_params), flat(loss.actor_network_params))
    torch.testing.assert_close(loss(td.clone())["loss_kl"], torch.tensor(0.0))


def test_mixup_is_trl_formula():
    loss, optim, td = setup()
    sync = ReferenceSync(loss, ref_model_sync_steps=1, ref_model_mixup_alpha=0.25)
    ref, policy = flat(loss.target_actor_network_params).clone(), None
    for _ in range(3):  # an EMA over successive updates
        train_step(loss, optim, td)
        policy = flat(loss.actor_network_params)
        sync.step()
        ref = 0.25 * policy + 0.75 * ref
        torch.testing.assert_close(flat(loss.target_actor_network_params), ref)


def test_counter_survives_state_dict():
    loss, _, _ = setup()
    sync = ReferenceSync(loss, ref_model_sync_steps=5)
    sync.step()
    sync.step()
    other = ReferenceSync(loss, ref_model_sync_steps=5)
    other.load_state_dict(sync.state_dict())
    assert other.counter == 2


def test_bad_setups_are_clear_errors():
    actor = categorical_actor()
    with pytest.raises(ValueError, match="no reference policy"):
        ReferenceSync(GRPOLoss(actor))
    loss = GRPOLoss(actor, kl_to_ref_coeff=0.0)
    with pytest.raises(ValueError, match="ref_model_sync_steps"):
        ReferenceSync(loss, ref_model_sync_steps=0)
    with pytest.raises(ValueError, match="ref_model_mixup_alpha"):
        ReferenceSync(loss, ref_model_mixup_alpha=0.0)
