"""One forward of the policy's network per minibatch, however many losses read it.

GRPO with branching sums up to three losses on each minibatch: the clipped surrogate,
the regression of the enumerated advantages (``algo.group_fit_coeff``) and the crash
head's cross-entropy (``model.crash_head``). Each is a TorchRL ``LossModule`` that runs
the actor itself, so the network ran three times on the same observations, and
backpropagated three times. Inside :func:`shared_forward` each network runs once per
input tensor: the later calls return the first call's output, graph included, so the
summed loss backpropagates through the network once. The gradient is the same sum,
accumulated at the network's output instead of at its parameters: equal up to float
rounding. With ``include_no_grad=True`` calls without grad are shared too, among
themselves: :class:`~torchrl_grpo.modules.GreedyTail` takes the learner's sampled and
greedy outputs on one rollout step from one forward.

Example:
    >>> import torch
    >>> class Counted(torch.nn.Linear):
    ...     runs = 0
    ...     def forward(self, x):
    ...         Counted.runs += 1
    ...         return super().forward(x)
    >>> net, x = Counted(3, 2), torch.ones(4, 3)
    >>> with shared_forward(net):
    ...     loss = net(x).sum() + net(x).pow(2).sum()  # two losses, one forward
    >>> loss.backward()
    >>> Counted.runs
    1
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn

from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.modules.ensemble import PolicyEnsemble

__all__ = ["shared_forward", "shared_networks"]


def shared_networks(policy: nn.Module) -> list[nn.Module]:
    """The networks :func:`shared_forward` runs once per input: what the actor calls.

    The network of every ``TensorDictModule`` in ``policy``; for a
    :class:`~torchrl_grpo.modules.CrashHead`, the network inside it (its policy logits
    and its crash logits are two slices of one output); for a
    :class:`~torchrl_grpo.modules.PolicyEnsemble`, those of its members.

    Example:
        >>> from torchrl.data import Categorical
        >>> from torchrl_grpo.modules import make_discrete_actor
        >>> net = nn.Linear(4, 6)
        >>> actor = make_discrete_actor(CrashHead(net, 3), Categorical(3))
        >>> shared_networks(actor) == [net]
        True
    """

    def inner(module: nn.Module) -> list[nn.Module]:
        if isinstance(module, CrashHead):
            return inner(module.net)
        if isinstance(module, PolicyEnsemble):
            return [net for member in module.members for net in inner(member)]
        return [module]

    found: list[nn.Module] = []
    for module in policy.modules():
        # A sequence (the actor itself) holds its modules in a list, not a network.
        if isinstance(module, TensorDictModule) and not isinstance(module, TensorDictSequential):
            found += [net for net in inner(module.module) if all(net is not f for f in found)]
    return found


def _memoised(net: nn.Module, include_no_grad: bool) -> Callable[..., torch.Tensor]:
    """``net.forward``, returning its last output again when nothing it reads has changed."""
    forward = net.forward
    # Per grad mode: what the last output was computed from, and the output. A no-grad
    # output never stands in for one with a graph, nor the other way round.
    last: dict[bool, list] = {True: [None, None], False: [None, None]}

    def inputs(x: torch.Tensor) -> tuple:
        # Every tensor the output depends on, by identity and version: TorchRL's losses
        # swap other parameters in (a reference policy's, ``to_module``), and an
        # optimiser step writes them in place.
        state = [*net.parameters(), *net.buffers()]
        return (x, *state), (x._version, *(t._version for t in state))

    def call(*args: object, **kwargs: object) -> torch.Tensor:
        x = args[0] if len(args) == 1 and not kwargs else None
        grad = torch.is_grad_enabled()
        # By default only outputs with a graph are shared: a no-grad call (a reference
        # policy's log-probs) neither uses nor replaces the kept output.
        if (
            not isinstance(x, torch.Tensor)
            or not (grad or include_no_grad)
            or torch.is_inference_mode_enabled()  # inference tensors have no versions
        ):
            return forward(*args, **kwargs)
        tensors, versions = inputs(x)
        kept = last[grad]
        seen = kept[0]
        if (
            seen is not None
            and seen[1] == versions
            and len(seen[0]) == len(tensors)
            and all(a is b for a, b in zip(seen[0], tensors, strict=True))
        ):
            return kept[1]
        out = forward(x)
        kept[0], kept[1] = (tensors, versions), out
        return out

    return call


@contextlib.contextmanager
def shared_forward(policy: nn.Module, include_no_grad: bool = False) -> Iterator[None]:
    """Within the block, each of ``policy``'s networks runs once per input tensor.

    For the losses of one minibatch: the last output of each network is kept (with
    its graph) until the block ends. A call with another tensor (even of equal
    values), with the input or a parameter written to since, with other parameters
    swapped in (a reference policy's, through TorchRL's ``to_module``) runs the network
    again. Calls without grad are not shared unless ``include_no_grad``: they run, and
    leave the kept output.

    Args:
        policy: the actor (see :func:`shared_networks`), or any module.
        include_no_grad: share calls without grad as well, among themselves (a rollout
            that acts twice on one observation, sampled then greedy); each grad mode
            keeps its own last output.

    Example:
        >>> net = nn.Linear(2, 1)
        >>> x = torch.ones(1, 2)
        >>> with shared_forward(net):
        ...     net(x) is net(x), net(x) is net(x.clone())
        (True, False)
    """
    nets = shared_networks(policy) or [policy]
    # An instance attribute shadows the class's forward for nn.Module.__call__.
    saved = [net.__dict__.get("forward") for net in nets]
    for net in nets:
        net.forward = _memoised(net, include_no_grad)
    try:
        yield
    finally:
        for net, own in zip(nets, saved, strict=True):
            del net.forward
            if own is not None:
                net.forward = own
