"""A categorical actor run in a branch worker without its TensorDict machinery.

A branch worker calls its copy of the policy once per step, on a batch of one row,
right after a simulator step. For the usual actor, TorchRL's
``ProbabilisticActor(TensorDictModule(net, [obs], ["logits"]), Categorical)``, the
modules around the network (key lookups, interaction-type dispatch, the
distribution's construction through TensorDict calls) cost more there than the
network: :class:`DirectActor` calls the network and ``torch.distributions.Categorical``
directly, writes the same entries, and takes 0.27 ms off a merge-v0 branch step of
11.5 ms (``benchmarks/bench_worker_step.py``, ``actor-modules`` against
``actor-direct``).

It only takes over where it is exact: :func:`direct_actor` recognises the actor's
structure (anything else is left to the actor), and the first sampled call of each
copy is the actor's own, repeated by the direct path on a copy of its input from the
same generator state: the direct path is kept only if every entry and the generator's
state after the call are bitwise the same.
"""

from __future__ import annotations

import logging

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import ProbabilisticActor, SafeProbabilisticModule

logger = logging.getLogger(__name__)

__all__ = ["DirectActor", "ProbedPolicy", "direct_actor"]


class DirectActor:
    """Samples a categorical actor's action from its network's logits, without TensorDict calls.

    Args:
        net: the logits network (a plain ``nn.Module``).
        in_key: the observation entry it reads.
        action_key: the entry of the sampled action.
        log_prob_key: the entry of its log-probability, or ``None`` when the actor
            writes none.

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.modules import make_discrete_actor
        >>> actor = make_discrete_actor(nn.Linear(3, 5), 5)
        >>> direct = direct_actor(actor)
        >>> td = TensorDict(observation=torch.zeros(1, 3), batch_size=[1])
        >>> _ = torch.manual_seed(0)
        >>> a = actor(td.clone())
        >>> _ = torch.manual_seed(0)
        >>> b = direct(td.clone())
        >>> bool((a["action"] == b["action"]).all()), sorted(b.keys()) == sorted(a.keys())
        (True, True)
    """

    def __init__(
        self, net: nn.Module, in_key: str, action_key: str, log_prob_key: str | None
    ) -> None:
        self.net = net
        self.in_key, self.action_key, self.log_prob_key = in_key, action_key, log_prob_key

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        """Write ``logits``, the sampled action and its log-probability into ``td``."""
        logits = self.net(td.get(self.in_key))
        dist = torch.distributions.Categorical(logits=logits)
        action = dist.sample()
        td.set("logits", logits)
        td.set(self.action_key, action)
        if self.log_prob_key is not None:
            td.set(self.log_prob_key, dist.log_prob(action))
        return td


def direct_actor(policy: object) -> DirectActor | None:
    """The direct path of ``policy`` if it is a plain categorical actor, else ``None``.

    A plain categorical actor is a ``ProbabilisticActor`` of two modules: a
    ``TensorDictModule`` whose module is a plain network from one observation entry
    to ``"logits"``, and a ``SafeProbabilisticModule`` that samples a
    ``torch.distributions.Categorical`` from them (no distribution arguments, no
    generator of its own, no samples count, no spec projection), writing the action
    and, optionally, its log-probability.
    """
    if type(policy) is not ProbabilisticActor or len(policy.module) != 2:
        return None
    logits_module, dist_module = policy.module
    if type(logits_module) is not TensorDictModule or type(dist_module) is not (
        SafeProbabilisticModule
    ):
        return None
    net = logits_module.module
    in_keys, out_keys = list(logits_module.in_keys), list(logits_module.out_keys)
    plain = (
        isinstance(net, nn.Module)
        and len(in_keys) == 1
        and isinstance(in_keys[0], str)
        and out_keys == ["logits"]
    )
    sampler = (
        dist_module.distribution_class is torch.distributions.Categorical
        and not dist_module.distribution_kwargs
        and list(dist_module.in_keys) == ["logits"]
        and getattr(dist_module, "_generator", None) is None
        and dist_module.num_samples is None
        and not dist_module.safe
    )
    if not (plain and sampler):
        return None
    outs = list(dist_module.out_keys)
    if not outs or not isinstance(outs[0], str):
        return None
    log_prob = dist_module.log_prob_key if dist_module.return_log_prob else None
    if outs != [outs[0], *([log_prob] if log_prob is not None else [])]:
        return None
    return DirectActor(net, in_keys[0], outs[0], log_prob)


class ProbedPolicy:
    """A policy called through its :class:`DirectActor` once that is shown exact here.

    The first call with random sampling is the policy's own; the direct path then
    runs on a copy of that call's input from the same state of torch's generator, and
    is kept for the next calls only if every entry it writes and the generator's
    state after it are bitwise the policy's. Calls of another exploration type run
    the policy itself.

    Args:
        policy: the policy.
    """

    def __init__(self, policy: object) -> None:
        self.policy = policy
        self.direct = direct_actor(policy)
        self.probed = self.direct is None

    def __call__(self, td: TensorDictBase) -> TensorDictBase | None:
        """Run the policy (or its exact direct path) on ``td``."""
        if self.direct is None or exploration_type() is not ExplorationType.RANDOM:
            return self.policy(td)
        if not self.probed:
            self.probed = True
            return self._probe(td)
        return self.direct(td)

    def _probe(self, td: TensorDictBase) -> TensorDictBase | None:
        """The policy's call on ``td``; drops the direct path if it does not repeat it."""
        start = torch.default_generator.get_state()
        copy = td.clone()
        result = self.policy(td)
        after = torch.default_generator.get_state()
        torch.default_generator.set_state(start)
        try:
            candidate = self.direct(copy)
        except Exception:  # noqa: BLE001 - the policy itself then runs
            candidate = None
        same_draws = torch.equal(torch.default_generator.get_state(), after)
        torch.default_generator.set_state(after)
        out = td if result is None else result
        if candidate is None or not same_draws or not _same(out, candidate):
            logger.debug("the direct path differs from the policy; the policy runs")
            self.direct = None
        return result


def _same(a: TensorDictBase, b: TensorDictBase) -> bool:
    keys = set(a.keys(True, True))
    if keys != set(b.keys(True, True)):
        return False
    for key in keys:
        x, y = a.get(key), b.get(key)
        if x.dtype != y.dtype or x.shape != y.shape or not torch.equal(x, y):
            return False
    return True
