import pytest
import torch

from torchrl_grpo.modules import EgoAttentionNet, KinematicsMLP
from torchrl_grpo.modules.networks import make_network

V, F = 5, 5


def _table(*batch: int, n_present: int = V) -> torch.Tensor:
    obs = torch.randn(*batch, V, F)
    obs[..., 0] = 0.0
    obs[..., :n_present, 0] = 1.0
    obs[..., n_present:, :] = 0.0
    return obs


@pytest.mark.parametrize("batch", [(), (3,), (2, 3, 4)])
def test_mlp_shapes(batch):
    net = KinematicsMLP(V, F, out_features=7, num_cells=(32,))
    assert net(_table(*batch)).shape == (*batch, 7)


@pytest.mark.parametrize("batch", [(), (3,), (2, 3, 4), (2, 1, 3, 2)])
def test_ego_attention_shapes(batch):
    net = EgoAttentionNet(F, out_features=7, embed_dim=16, num_heads=4)
    assert net(_table(*batch)).shape == (*batch, 7)
    assert net.attention_weights(_table(*batch)).shape == (*batch, 4, V)


def test_ego_attention_matches_per_sample_calls():
    torch.manual_seed(0)
    net = EgoAttentionNet(F, out_features=3, embed_dim=16, num_heads=2)
    obs = _table(2, 3, n_present=3)
    batched = net(obs)
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(batched[i, j], net(obs[i, j]))


def test_ego_attention_empty_batch():
    net = EgoAttentionNet(F, out_features=3, embed_dim=8, num_heads=2)
    assert net(torch.zeros(0, 4, V, F)).shape == (0, 4, 3)


def test_presence_mask_ignores_absent_vehicles():
    torch.manual_seed(0)
    net = EgoAttentionNet(F, out_features=4, embed_dim=16, num_heads=2)
    obs = _table(6, n_present=3)
    changed = obs.clone()
    # Absent rows keep presence 0 but get arbitrary (even huge) features.
    changed[:, 3:, 1:] = torch.randn(6, 2, F - 1) * 100
    torch.testing.assert_close(net(changed), net(obs), rtol=0, atol=0)
    weights = net.attention_weights(obs)
    assert torch.all(weights[..., 3:] == 0)
    torch.testing.assert_close(weights.sum(-1), torch.ones(6, 2))


def test_present_vehicles_do_change_output():
    torch.manual_seed(0)
    net = EgoAttentionNet(F, out_features=4, embed_dim=16, num_heads=2)
    obs = _table(6, n_present=3)
    changed = obs.clone()
    changed[:, 2, 1:] += 1.0
    assert not torch.allclose(net(changed), net(obs))


def test_without_mask_absent_vehicles_matter():
    torch.manual_seed(0)
    net = EgoAttentionNet(F, out_features=4, embed_dim=16, num_heads=2, presence_index=None)
    obs = _table(6, n_present=3)
    changed = obs.clone()
    changed[:, 4, 1:] = 5.0
    assert not torch.allclose(net(changed), net(obs))


def test_invariant_to_order_of_other_vehicles():
    torch.manual_seed(0)
    net = EgoAttentionNet(F, out_features=4, embed_dim=16, num_heads=2)
    obs = _table(6)
    permuted = obs[:, [0, 3, 1, 4, 2]]
    torch.testing.assert_close(net(permuted), net(obs))


def test_all_zero_padding_gives_finite_output():
    # Steps padded with zeros after an episode ends have no present vehicle at all.
    net = EgoAttentionNet(F, out_features=4, embed_dim=16, num_heads=2)
    out = net(torch.zeros(3, V, F))
    assert torch.isfinite(out).all()


def test_gradients_flow_through_attention():
    net = EgoAttentionNet(F, out_features=2, embed_dim=8, num_heads=2)
    net(_table(4, n_present=2)).sum().backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


def test_shape_errors_are_clear():
    net = EgoAttentionNet(F, out_features=2, embed_dim=8, num_heads=2, n_vehicles=V)
    with pytest.raises(ValueError, match="vehicle rows"):
        net(torch.zeros(2, V + 1, F))
    with pytest.raises(ValueError, match="shape"):
        KinematicsMLP(V, F, 2)(torch.zeros(2, V, F + 1))
    with pytest.raises(ValueError, match="divide"):
        EgoAttentionNet(F, 2, embed_dim=10, num_heads=3)


def test_make_network():
    assert isinstance(
        make_network("mlp", n_vehicles=V, n_features=F, out_features=2), KinematicsMLP
    )
    net = make_network("ego_attention", n_vehicles=V, n_features=F, out_features=2, embed_dim=8)
    assert isinstance(net, EgoAttentionNet)
    with pytest.raises(ValueError, match="Unknown"):
        make_network("cnn", n_vehicles=V, n_features=F, out_features=2)  # type: ignore[arg-type]


def test_the_vehicle_transformer_ignores_the_order_and_the_features_of_absent_vehicles():
    from torchrl_grpo.modules import VehicleTransformer

    torch.manual_seed(0)
    net = VehicleTransformer(n_features=5, out_features=3, presence_index=0, embed_dim=16, width=8)
    obs = torch.randn(4, 6, 5)
    obs[..., 0] = torch.tensor([1.0, 1.0, 1.0, 0.0, 1.0, 0.0])  # rows 3 and 5 absent
    net.standardise_from(obs)
    out = net(obs)
    shuffled = obs[:, [0, 4, 2, 1, 5, 3]]  # the ego stays first
    torch.testing.assert_close(net(shuffled), out)
    noise = obs.clone()
    noise[:, 3, 1:] += 10.0
    torch.testing.assert_close(net(noise), out)
    changed = obs.clone()
    changed[:, 1, 1:] += 1.0  # a present vehicle moves: the output does too
    assert not torch.allclose(net(changed), out)
    # The statistics are those of the present rows; the presence column stays as it is.
    present = obs.reshape(-1, 5)[obs.reshape(-1, 5)[:, 0] > 0.5]
    torch.testing.assert_close(net.mean[1:], present[:, 1:].mean(0))
    assert (float(net.mean[0]), float(net.std[0])) == (0.0, 1.0)


def test_the_vehicle_transformer_names_a_bad_table_or_size():
    from torchrl_grpo.modules import VehicleTransformer

    with pytest.raises(ValueError, match="num_heads=3 must divide embed_dim=16"):
        VehicleTransformer(5, 3, presence_index=0, embed_dim=16, num_heads=3)
    net = VehicleTransformer(5, 3, presence_index=0, embed_dim=16)
    with pytest.raises(ValueError, match=r"shape \[\*batch, V, 5\], got \(2, 4\)"):
        net(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="at least two present vehicle rows"):
        net.standardise_from(torch.zeros(3, 4, 5))
