"""The Ray backend: equivalence with the local collector, faults, training (needs Ray)."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path

import pytest
import torch

ray = pytest.importorskip("ray")

import distributed_helpers  # noqa: E402
from distributed_helpers import (  # noqa: E402
    ENV_FACTORY,
    SMALL,
    SlowPolicy,
    assert_bitwise_equal,
    local_reference,
    make_policy,
)

from torchrl_grpo.branching import GROUP_ID, MASK  # noqa: E402
from torchrl_grpo.branching.keys import TRAJ_IDS  # noqa: E402
from torchrl_grpo.distributed import RayGroupCollector, init_ray  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def ray_session():
    """One small local Ray for the module (2 CPUs, 128 MiB object store, no dashboard)."""
    started = init_ray(num_cpus=2, object_store_memory=128 * 1024**2)
    # Actors unpickle the helpers' classes: ship them by value (tests/ is no package).
    ray.cloudpickle.register_pickle_by_value(distributed_helpers)
    yield
    if started:
        ray.shutdown()


def collect(collector: RayGroupCollector, batches: int) -> list:
    out = []
    with collector:
        for batch in collector:
            out.append(batch)
            if len(out) == batches:
                break
    return out


def check_structure(batches, groups_per_batch: int, group_size: int) -> None:
    """Group ids 0, 1, 2, ... once each; traj ids follow them; branches 0..G-1."""
    ids = torch.cat([b[GROUP_ID][:, 0, 0] for b in batches])
    assert ids.tolist() == list(range(len(batches) * groups_per_batch))
    for b in batches:
        assert (b[GROUP_ID] == b[GROUP_ID][:, :1, :1]).all()
        assert (b["branch"][:, :, 0] == torch.arange(group_size)).all()
        assert (b[TRAJ_IDS] == b[GROUP_ID] * group_size + b["branch"]).all()


def test_one_actor_matches_local_collector():
    policy = make_policy()
    kwargs = dict(SMALL, roots="trunk", decision_interval=2)
    got = collect(
        RayGroupCollector(
            ENV_FACTORY,
            policy,
            num_actors=1,
            groups_per_batch=2,
            seed=3,
            num_cpus_per_actor=0.5,
            **kwargs,
        ),
        3,
    )
    want = local_reference(policy, seed=3, num_actors=1, groups_per_batch=2, batches=3, **kwargs)
    for g, w in zip(got, want, strict=True):
        assert_bitwise_equal(g, w)
    check_structure(got, 2, 2)


@pytest.mark.slow  # the default suite's 10-minute budget
def test_actors_match_local_runs_of_their_seeds():
    policy = make_policy()
    kwargs = dict(SMALL, roots="reset", rng="per_branch")
    collector = RayGroupCollector(
        ENV_FACTORY,
        policy,
        num_actors=2,
        groups_per_batch=3,
        seed=0,
        num_cpus_per_actor=0.5,
        **kwargs,
    )
    got = collect(collector, 2)
    want = local_reference(policy, seed=0, num_actors=2, groups_per_batch=3, batches=2, **kwargs)
    for g, w in zip(got, want, strict=True):
        assert g.batch_size == (3, 2, 2)
        assert_bitwise_equal(g, w)
    check_structure(got, 3, 2)
    assert collector.frames == sum(int(b[MASK].sum()) for b in got)


@pytest.mark.slow  # the default suite's 10-minute budget
def test_killed_actor_is_replaced_and_its_batch_redone():
    policy = SlowPolicy(make_policy(), delay=0.1)
    kwargs = dict(SMALL, roots="trunk", decision_interval=2)
    collector = RayGroupCollector(
        ENV_FACTORY,
        policy,
        num_actors=2,
        groups_per_batch=2,
        seed=1,
        num_cpus_per_actor=0.5,
        **kwargs,
    )
    got = []
    with collector:
        it = iter(collector)
        got.append(next(it))  # the actors are up
        pid = ray.get(collector.actors[0].pid.remote())
        # SIGKILL actor 0 while its second batch runs (each batch takes >= 0.4 s).
        killer = threading.Timer(0.15, os.kill, (pid, signal.SIGKILL))
        killer.start()
        got.append(next(it))
        killer.join()
        got.append(next(it))
        frames, trunk_frames, restarts = (
            collector.frames,
            collector.trunk_frames,
            collector.restarts,
        )
        assert ray.get(collector.actors[0].pid.remote()) != pid
    assert restarts == 1
    want = local_reference(
        policy.policy, seed=1, num_actors=2, groups_per_batch=2, batches=3, **kwargs
    )
    for g, w in zip(got, want, strict=True):
        assert_bitwise_equal(g, w)
    check_structure(got, 2, 2)
    # Exact counts: the dead actor's partial work is neither lost nor counted.
    assert frames == sum(int(b[MASK].sum()) for b in got)
    assert trunk_frames > 0


@pytest.mark.slow
def test_actor_killed_between_batches_is_replaced():
    policy = make_policy()
    collector = RayGroupCollector(
        ENV_FACTORY,
        policy,
        num_actors=2,
        groups_per_batch=2,
        seed=2,
        num_cpus_per_actor=0.5,
        roots="reset",
        **SMALL,
    )
    got = []
    with collector:
        it = iter(collector)
        got.append(next(it))
        ray.kill(collector.actors[1], no_restart=True)
        got.append(next(it))
        assert collector.restarts == 1
    want = local_reference(
        policy, seed=2, num_actors=2, groups_per_batch=2, batches=2, roots="reset", **SMALL
    )
    for g, w in zip(got, want, strict=True):
        assert_bitwise_equal(g, w)


def test_weights_reach_the_actors():
    policy = make_policy()
    with RayGroupCollector(
        ENV_FACTORY,
        policy,
        num_actors=1,
        groups_per_batch=1,
        seed=0,
        num_cpus_per_actor=0.5,
        roots="reset",
        **SMALL,
    ) as collector:
        it = iter(collector)
        next(it)
        # The learner's update: logits that make action 3 certain.
        with torch.no_grad():
            last = [m for m in policy.modules() if isinstance(m, torch.nn.Linear)][-1]
            last.weight.zero_()
            last.bias.copy_(torch.tensor([0.0, 0.0, 0.0, 100.0, 0.0]))
        batch = next(it)
    assert (batch["action"][batch[MASK]] == 3).all()


# ---------------------------------------------------------------- refused states (#20)
def _refused_states(n_good: int):
    """A sample of corrupted merge-v0 root states, each refused at restore, and good roots.

    Returns ``(bad, good, names)``: ``bad[k]`` is refused naming ``names[k]``.
    """
    from torchrl_grpo.branching import reset_roots
    from torchrl_grpo.envs import HighwayEnv

    env = HighwayEnv("merge-v0", seed=0)
    good = reset_roots(env, n_good)
    layout = env.codec.layout
    obstacle = env.codec.max_vehicles  # merge-v0's road object: an Obstacle

    def f64(state, field, slot, value):
        column = layout.columns[field].start
        state["sim", "entities", "f64"].view(torch.float64)[:, slot, column] = value

    corruptions = {
        r"env\.rng": lambda s: s["sim", "env", "rng"].fill_(0),
        r"entities\.speed": lambda s: f64(s, "speed", 1, float("nan")),
        r"entities\.heading": lambda s: f64(s, "heading", 0, float("inf")),
        r"output\.observation": lambda s: (
            s["output", "observation"].view(torch.float32).fill_(float("nan"))
        ),
        r"env\.controlled": lambda s: s["sim", "env", "controlled"].fill_(obstacle),
        r"env\.class_params": lambda s: s["sim", "env", "class_params"].fill_(0),
        r"wrappers\.has_reset": lambda s: s["sim", "wrappers", "has_reset"].fill_(False),
        "kind": lambda s: s["sim", "entities", "i16"][:, 1, 0].fill_(7),
    }
    bad = []
    for corrupt in corruptions.values():
        root = good[:1].clone()  # states of a batch of one root
        corrupt(root["state"])
        bad.append(root)
    return bad, good, list(corruptions)


def test_a_refused_state_reaches_the_caller_and_the_actor_steps_on():
    from torchrl_grpo.branching import StoredRoots
    from torchrl_grpo.distributed.worker import GroupWorker
    from torchrl_grpo.envs import StateCorruptedError

    bad, good, names = _refused_states(2)
    # the actor's roots alternate: a refused one, then a good one
    roots = torch.cat([torch.cat([b, good[k % 2 : k % 2 + 1]]) for k, b in enumerate(bad)])
    kwargs = dict(SMALL, groups_per_batch=1, roots=StoredRoots(roots))
    actor = (
        ray.remote(GroupWorker)
        .options(num_cpus=0.5)
        .remote(ENV_FACTORY, make_policy(), kwargs, 0, 1)
    )
    try:
        pid = ray.get(actor.pid.remote())
        for k, name in enumerate(names):
            with pytest.raises(StateCorruptedError, match=name):
                ray.get(actor.collect.remote(None, 2 * k))
            result = ray.get(actor.collect.remote(None, 2 * k + 1))
            assert result.data is not None and result.data[MASK].all(), name
            # the branches start from that good root
            want = good["state", "output", "observation"][k % 2].view(torch.float32)
            assert (result.data["observation"][0, :, 0] == want).all(), name
        assert ray.get(actor.pid.remote()) == pid  # the same process all along
    finally:
        ray.get(actor.close.remote())
        ray.kill(actor, no_restart=True)


@pytest.mark.slow  # one more actor start (about 5 s)
def test_a_refused_state_stops_a_ray_collection_with_its_error_not_a_restart():
    from torchrl_grpo.branching import StoredRoots
    from torchrl_grpo.envs import StateCorruptedError

    bad, good, names = _refused_states(1)
    collector = RayGroupCollector(
        ENV_FACTORY,
        make_policy(),
        num_actors=1,
        groups_per_batch=1,
        seed=0,
        num_cpus_per_actor=0.5,
        roots=StoredRoots(torch.cat([good, bad[0]])),
        wait_timeout=60.0,
        **SMALL,
    )
    it = iter(collector)
    assert next(it)[MASK].all()
    with pytest.raises(StateCorruptedError, match=names[0]):
        next(it)
    assert collector.restarts == 0  # an error of the collection, not an actor that died
    assert not collector.actors  # and the collection stopped, its actors ended


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    from torchrl_grpo.training import register_configs

    register_configs()
    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(str(conf), version_base=None):
        return compose("config", overrides=overrides)


TINY_RAY = [
    "experiment=smoke",
    "logger=none",
    "experiment.eval_every=0",
    "experiment.final_eval_episodes=0",
    "experiment.checkpoint_every=1",
    "rollout=ray",
    "rollout.ray.num_actors=2",
    "rollout.ray.num_cpus_per_actor=0.5",
    "env.backend=tensor",  # the recipe as it trains: tensor shards, rule tails, replay
    "env.num_envs=10",
]


@pytest.mark.slow
def test_training_on_ray_resumes_exactly(tmp_path):
    from torchrl_grpo.training import Trainer

    straight = Trainer(
        _compose([*TINY_RAY, "experiment.total_frames=150"]), run_dir=tmp_path / "straight"
    )
    result = straight.train()
    assert result.frames >= 150 and result.iterations >= 2
    first = Trainer(_compose([*TINY_RAY, "experiment.total_frames=20"]), run_dir=tmp_path / "a")
    half = first.train()
    resumed = Trainer(
        _compose([*TINY_RAY, "experiment.total_frames=150", f"resume={half.checkpoint}"]),
        run_dir=tmp_path / "b",
    )
    end = resumed.train()
    assert (end.frames, end.iterations) == (result.frames, result.iterations)
    for key, value in straight.policy.state_dict().items():
        assert torch.equal(value, resumed.policy.state_dict()[key]), key
