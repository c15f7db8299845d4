"""Shared helpers of the Ray tests: a slow policy and the local reference runs."""

from __future__ import annotations

import functools
import time

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_grpo.branching import GroupCollector, make_branch_env
from torchrl_grpo.distributed.actor_pool import split_groups
from torchrl_grpo.distributed.worker import actor_seed
from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor

ENV_FACTORY = functools.partial(make_branch_env, "merge-v0", 1, backend="single")
SMALL = dict(group_size=2, horizon=2)


def make_policy(seed: int = 0) -> TensorDictModuleBase:
    torch.manual_seed(seed)
    return make_discrete_actor(KinematicsMLP(5, 5, out_features=5, num_cells=[16]), 5)


class SlowPolicy(TensorDictModuleBase):
    """The wrapped policy, ``delay`` seconds slower per call (a kill lands mid-batch)."""

    def __init__(self, policy: TensorDictModuleBase, delay: float) -> None:
        super().__init__()
        self.policy = policy
        self.delay = delay
        self.in_keys = policy.in_keys
        self.out_keys = policy.out_keys

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        time.sleep(self.delay)
        return self.policy(tensordict)


def local_reference(
    policy, *, seed: int, num_actors: int, groups_per_batch: int, batches: int, **kwargs
) -> list[TensorDictBase]:
    """What RayGroupCollector must yield: per-actor local collectors, concatenated.

    Actor a is a local GroupCollector seeded with actor_seed(seed, a), torch seeded the
    same right after it is built, its group ids set to those the learner assigns.
    """
    counts = split_groups(groups_per_batch, num_actors)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in the actors
    per_actor = []
    try:
        for a, n in enumerate(counts):
            s = actor_seed(seed, a)
            out = []
            with GroupCollector(
                ENV_FACTORY(), policy, groups_per_batch=n, seed=s, **kwargs
            ) as collector:
                torch.manual_seed(s)
                for k in range(batches):
                    state = collector.state_dict()
                    state["next_group_id"] = k * groups_per_batch + sum(counts[:a])
                    collector.load_state_dict(state)
                    out.append(next(iter(collector)))
            per_actor.append(out)
    finally:
        torch.set_num_threads(threads)
    return [torch.cat([per_actor[a][k] for a in range(num_actors)]) for k in range(batches)]


def assert_bitwise_equal(got: TensorDictBase, want: TensorDictBase) -> None:
    assert got.batch_size == want.batch_size
    keys = set(want.keys(True, True))
    assert set(got.keys(True, True)) == keys
    differ = [k for k in keys if not torch.equal(got.get(k), want.get(k))]
    assert not differ, f"entries differ: {differ}"
