"""shared_forward: one forward per input tensor, with the same values and gradients."""

from __future__ import annotations

import pytest
import torch
from modules_helpers import Counted
from tensordict import TensorDict
from torchrl.data import Categorical

from torchrl_grpo.modules import CrashHead, PolicyEnsemble, make_discrete_actor
from torchrl_grpo.modules.forward_sharing import shared_forward, shared_networks


def test_the_networks_are_the_ones_the_actor_calls():
    plain = Counted(4, 3)
    assert shared_networks(make_discrete_actor(plain, Categorical(3))) == [plain]
    inner = Counted(4, 6)
    assert shared_networks(make_discrete_actor(CrashHead(inner, 3), Categorical(3))) == [inner]
    members = [Counted(4, 6), Counted(4, 6)]
    ensemble = PolicyEnsemble([CrashHead(m, 3) for m in members])
    assert shared_networks(make_discrete_actor(ensemble, Categorical(3))) == members


def test_a_crash_heads_two_outputs_and_the_actor_share_one_run_and_one_gradient():
    torch.manual_seed(0)
    net = Counted(4, 6)
    head = CrashHead(net, 3, aversion=2.0)
    actor = make_discrete_actor(head, Categorical(3))
    x = torch.randn(8, 4)

    def losses() -> torch.Tensor:
        # Three consumers, as GRPO's surrogate, the regression and the crash head.
        dist = actor.get_dist(TensorDict(observation=x, batch_size=[8]))
        return dist.logits.pow(2).sum() + head(x).sum() + head.crash_logits(x).exp().sum()

    separate = losses()
    separate.backward()
    alone = [p.grad.clone() for p in net.parameters()]
    assert net.runs == 3
    net.zero_grad()
    net.runs = 0
    with shared_forward(actor):
        shared = losses()
    shared.backward()
    assert net.runs == 1
    torch.testing.assert_close(shared, separate)
    for a, b in zip(alone, (p.grad for p in net.parameters()), strict=True):
        torch.testing.assert_close(a, b)


def test_only_the_same_unmodified_tensor_in_the_same_grad_mode_is_shared():
    net = Counted(2, 1)
    x = torch.ones(3, 2)
    with shared_forward(net):
        first = net(x)
        assert net(x) is first and net.runs == 1
        assert net(x.clone()) is not first  # equal values, another tensor: runs again
        with torch.no_grad():
            no_graph = net(x)
        assert not no_graph.requires_grad
        assert net(x).requires_grad  # a no-grad output never stands in for a graph
        runs = net.runs
        x.add_(1.0)  # written in place: its version moved
        torch.testing.assert_close(net(x), net.linear(x))
        assert net.runs == runs + 1


def test_no_grad_calls_are_shared_among_themselves_when_asked():
    net = Counted(2, 1)
    x = torch.ones(3, 2)
    with shared_forward(net), torch.no_grad():
        net(x), net(x)
    assert net.runs == 2  # by default a no-grad call always runs
    net.runs = 0
    with shared_forward(net, include_no_grad=True):
        with torch.no_grad():
            kept = net(x)
            assert net(x) is kept and net.runs == 1
        graph = net(x)  # the grad mode keeps its own output
        assert graph.requires_grad and net.runs == 2
        with torch.no_grad():
            assert net(x) is kept and net.runs == 2  # and the no-grad one survives it
        with torch.inference_mode():
            net(x), net(x)  # inference tensors have no version to key on: never shared
        assert net.runs == 4


def test_the_networks_forward_is_restored_after_the_block_even_on_an_error():
    net = Counted(2, 1)
    own = net.forward
    net.forward = lambda x: own(x) * 2  # an instance forward of the user's own
    mine = net.forward
    with pytest.raises(RuntimeError, match="boom"), shared_forward(net):
        assert net.forward is not mine
        raise RuntimeError("boom")
    assert net.forward is mine
    plain = Counted(2, 1)
    with shared_forward(plain):
        pass
    assert "forward" not in vars(plain)
    x = torch.ones(1, 2)
    plain(x)
    plain(x)
    assert plain.runs == 2  # outside the block every call runs


def test_other_or_updated_parameters_run_the_network_again():
    net = Counted(2, 2)
    x = torch.ones(3, 2)
    reference = TensorDict.from_module(net).clone().apply(lambda t: t + 1.0)
    expected = x @ (net.linear.weight + 1).T + net.linear.bias + 1
    with shared_forward(net):
        policy = net(x)
        # A reference policy's parameters swapped in, as GRPOLoss's KL term does.
        with torch.no_grad(), reference.to_module(net):
            torch.testing.assert_close(net(x), expected)
        assert net(x) is policy  # the no-grad call left the policy's output kept
        with reference.to_module(net):
            torch.testing.assert_close(net(x), expected)  # with grad: told apart too
        with torch.no_grad():
            net.linear.bias.add_(1.0)  # an optimiser step
        torch.testing.assert_close(net(x), policy.detach() + 1.0)
    assert net.runs == 4
