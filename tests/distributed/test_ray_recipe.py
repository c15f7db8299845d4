"""The recommended recipe on Ray actors: tensor shards, scripted tails, live trunks.

The actor (:class:`GroupWorker`) is a plain class, so these tests run without Ray: an
actor is shipped its policy and its root source apart (as Ray pickles them), gets new
weights every batch, and must yield bitwise the local collector's batches.
"""

from __future__ import annotations

import copy
from unittest import mock

import pytest
import torch
from distributed_helpers import assert_bitwise_equal
from tensordict import TensorDict

from torchrl_grpo.branching import GroupCollector
from torchrl_grpo.branching.roots import TrunkRoots
from torchrl_grpo.distributed.worker import GroupWorker, shared_root_policy
from torchrl_grpo.modules.greedy_tail import GreedyTail
from torchrl_grpo.training import GRPO, compose_config, make_env, make_policy
from torchrl_grpo.training.config_checks import check_config
from torchrl_grpo.training.ray_rollout import actor_env

# The recipe (scripted rule tails after 7 learner steps, replay, live staggered trunks)
# at test size, on the tensor simulator.
RECIPE_ON_RAY = [
    "experiment=smoke",
    "env.backend=tensor",
    "env.num_envs=10",
    "rollout=ray",
    "rollout.ray.num_actors=1",
    "rollout.groups_per_batch=2",
    "rollout.decision_interval=1",
]


def _recipe_parts():
    """The recipe's tails wrapper and trunk source, as the trainer hands them to Ray."""
    cfg = compose_config(RECIPE_ON_RAY)
    check_config(cfg)  # the scripted tails and the replay are accepted on Ray
    env = make_env(cfg.env, seed=0)
    torch.manual_seed(0)
    grpo = GRPO(cfg, make_policy(cfg.model, env), env)
    with mock.patch("torchrl_grpo.training.collect.make_ray_collector") as ray_collector:
        grpo.make_collector(seed=0)
    tails, source = ray_collector.call_args.args[1:3]
    return grpo.cfg, grpo.policy, tails, source


def _nudge(learner: torch.nn.Module, step: int) -> None:
    with torch.no_grad():
        for p in learner.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(step)))


def test_the_recipe_is_accepted_on_ray_and_its_trunks_follow_the_learner():
    cfg, learner, tails, source = _recipe_parts()
    assert isinstance(tails, GreedyTail) and str(cfg.algo.tail_policy) == "rule"
    assert isinstance(source, TrunkRoots) and source.live and source.stagger > 0
    assert source.policy is learner and shared_root_policy(tails, source) == "policy"
    assert shared_root_policy(tails, TrunkRoots(1)) is None  # the collector's own policy


def test_an_actor_on_a_tensor_shard_collects_the_local_batches_bitwise():
    cfg, learner, tails, source = _recipe_parts()
    factory, options = actor_env(cfg)
    assert factory().batch_size == (10,) and "num_gpus" not in options
    kwargs = dict(
        group_size=int(cfg.algo.group_size),
        horizon=int(cfg.rollout.horizon),
        groups_per_batch=int(cfg.rollout.groups_per_batch),
        decision_interval=int(cfg.rollout.decision_interval),
        select=str(cfg.algo.select),
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in an actor
    try:
        # Local: the learner's own objects, new weights before every batch.
        local_tails, local_source = copy.deepcopy((tails, source))  # linked, as in training
        want, weights = [], []
        collector = GroupCollector(factory(), local_tails, roots=local_source, seed=5, **kwargs)
        torch.manual_seed(5)
        batches = iter(collector)
        for step in range(3):
            _nudge(local_tails.policy, step)
            weights.append(TensorDict.from_module(local_tails).data.clone())
            want.append(next(batches))
        collector.shutdown()
        assert want[0]["explored"].any() and not want[0]["explored"].all()

        # The actor: its policy and root source arrive as separate copies.
        def actor(seed: int) -> GroupWorker:
            roots = copy.deepcopy(source)
            return GroupWorker(
                factory,
                copy.deepcopy(tails),
                dict(kwargs, roots=roots),
                seed=seed,
                num_threads=1,
                root_policy=shared_root_policy(tails, source),
            )

        worker = actor(5)
        got, snapshots = [], []
        for step in range(3):
            result = worker.collect(weights[step], first_group_id=2 * step)
            got.append(result.data)
            snapshots.append(copy.deepcopy(result.snapshot))
        worker.close()
        for g, w in zip(got, want, strict=True):
            assert_bitwise_equal(g, w)

        # A replacement restored from the first batch's snapshot redoes the next ones.
        replacement = actor(99)
        replacement.restore(snapshots[0])
        for step in (1, 2):
            redone = replacement.collect(weights[step], first_group_id=2 * step).data
            assert_bitwise_equal(redone, want[step])
        replacement.close()
    finally:
        torch.set_num_threads(threads)


def test_without_the_link_the_trunks_would_keep_the_first_weights():
    # The failure the link prevents: the root source's own copy of the learner.
    cfg, learner, tails, source = _recipe_parts()
    actor_tails, roots = copy.deepcopy(tails), copy.deepcopy(source)
    assert roots.policy is not actor_tails.policy
    worker = GroupWorker(
        actor_env(cfg)[0],
        actor_tails,
        dict(group_size=5, horizon=8, groups_per_batch=2, roots=roots),
        seed=0,
        num_threads=None,
        root_policy="policy",
    )
    assert worker.collector.root_source.policy is worker.collector.policy.policy
    worker.close()


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_actor_env_reserves_a_gpu_per_actor_on_cuda(device):
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a GPU")
    cfg = compose_config([*RECIPE_ON_RAY, f"device={device}", "rollout.ray.num_actors=2"])
    factory, options = actor_env(cfg)
    assert factory.keywords["num_envs"] == 5 and factory.keywords["device"] == device
    assert options.get("num_gpus") == (1 if device == "cuda" else None)
