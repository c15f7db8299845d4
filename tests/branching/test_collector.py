"""GroupCollector: batches, frame counting, unique group ids, root kinds, seeding, shutdown."""

from __future__ import annotations

import copy

import pytest
import torch
from branching_helpers import ScheduledPolicy, branch_env, plain_env
from tensordict import TensorDict
from torchrl.collectors import BaseCollector

from torchrl_grpo.branching import GroupCollector, StoredRoots, make_branch_env, reset_roots
from torchrl_grpo.envs import states_equal
from torchrl_grpo.modules import KinematicsMLP, RandomPolicy, make_discrete_actor


def test_batches_frames_and_unique_group_ids(no_workers_left):
    env = branch_env("highway-fast-v0", "parallel", config={"duration": 3})
    collector = GroupCollector(
        env,
        RandomPolicy(seed=0),
        group_size=2,
        horizon=4,
        groups_per_batch=2,
        total_frames=30,
        seed=0,
    )
    assert isinstance(collector, BaseCollector)
    batches = list(collector)
    # Episodes last 3 steps: each batch counts 2 * 2 * 3 = 12 frames, not 16.
    assert [int(b["mask"].sum()) for b in batches] == [12, 12, 12]
    assert collector.frames == 36
    ids = torch.cat([b["group_id"][:, 0, 0] for b in batches])
    assert ids.tolist() == list(range(6))
    for b in batches:
        assert b.batch_size == (2, 2, 4)
        assert (b["group_id"] == b["group_id"][:, :1, :1]).all()
    # Reaching total_frames closed the workers.
    assert env.is_closed


def test_trunk_roots_in_collector():
    env = branch_env("merge-v0", "serial")
    with GroupCollector(
        env,
        ScheduledPolicy(torch.ones(2, 2)),
        group_size=2,
        horizon=2,
        groups_per_batch=3,
        total_frames=12,
        roots="trunk",
        decision_interval=2,
        seed=0,
    ) as collector:
        batch = next(iter(collector))
        steps = batch["root_step"][:, 0, 0].tolist()
        # Decision points of the first trunk, every 2 steps (it may end early).
        assert steps[:2] == [0, 2] and all(s % 2 == 0 for s in steps)
        assert collector.trunk_frames >= 3


def test_continue_roots_follow_the_selected_branch():
    env = branch_env("highway-fast-v0", "serial")
    with GroupCollector(
        env,
        RandomPolicy(seed=0),
        group_size=3,
        horizon=2,
        groups_per_batch=2,
        roots="continue",
        select="best",
        return_states=True,
        seed=0,
    ) as collector:
        it = iter(collector)
        first, second = next(it), next(it)
    pick = first["selected"][:, :, 0].float().argmax(1)
    assert torch.equal(pick, first["branch_return"][:, :, 0, 0].argmax(1))
    for r in range(2):
        chosen = first[r, pick[r]]
        end = chosen["next", "state"][int(chosen["mask"].sum()) - 1]
        assert states_equal(second["state"][r, 0, 0], end)
    assert second["root_step"][:, 0, 0].tolist() == [2, 2]
    assert second["group_id"][:, 0, 0].tolist() == [2, 3]


def test_reset_roots_never_repeat_an_episode_after_branching():
    # Restores overwrite the workers' generators; unseeded resets would replay episodes.
    env = branch_env("highway-fast-v0", "serial")
    with GroupCollector(
        env,
        RandomPolicy(seed=0),
        group_size=2,
        horizon=1,
        groups_per_batch=2,
        total_frames=12,
        return_states=True,
        seed=0,
    ) as collector:
        starts = torch.cat([b["state", "sim"][:, 0, 0] for b in collector])
    assert starts.shape[0] == 6
    for i in range(6):
        for j in range(i):
            assert not states_equal(starts[i], starts[j]), (i, j)


def test_stored_roots_run_out():
    roots = reset_roots(plain_env("merge-v0", seed=0), 3)
    env = plain_env("merge-v0")
    with GroupCollector(
        env,
        RandomPolicy(seed=0),
        group_size=2,
        horizon=2,
        groups_per_batch=2,
        roots=StoredRoots(roots),
    ) as collector:
        sizes = [b.shape[0] for b in collector]
    assert sizes == [2, 1]


def _batches(seed: int, n: int = 2) -> list[TensorDict]:
    torch.manual_seed(seed)
    env = branch_env("merge-v0", "serial")
    policy = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
    with GroupCollector(
        env, policy, group_size=2, horizon=2, groups_per_batch=2, seed=seed, total_frames=16
    ) as collector:
        return list(collector)[:n]


def test_seeding_reproduces_batches():
    a, b, c = _batches(1), _batches(1), _batches(2)
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x["next", "observation"], y["next", "observation"])
        assert torch.equal(x["action"], y["action"])
    assert not torch.equal(a[0]["observation"], c[0]["observation"])


def test_update_policy_weights_and_state_dict():
    policy = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
    trained = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
    env = plain_env("merge-v0", seed=0)
    with GroupCollector(env, policy, group_size=2, horizon=1, groups_per_batch=1) as collector:
        collector.update_policy_weights_(trained)
        for p, q in zip(policy.parameters(), trained.parameters(), strict=True):
            assert torch.equal(p, q)
        collector.update_policy_weights_()  # a no-op: the policy is used in place
        next(iter(collector))
        state = collector.state_dict()
    assert state["frames"] == 2 and state["next_group_id"] == 1
    env2 = plain_env("merge-v0", seed=0)
    with GroupCollector(env2, policy, group_size=2, horizon=1, groups_per_batch=1) as other:
        other.load_state_dict(state)
        assert next(iter(other))["group_id"].unique().tolist() == [1]


@pytest.mark.parametrize("roots", ["reset", "trunk", "continue"])
def test_a_collector_continues_exactly_from_its_state_dict(roots):
    def build() -> GroupCollector:
        return GroupCollector(
            plain_env("highway-fast-v0"),
            RandomPolicy(seed=0),
            group_size=2,
            horizon=2,
            groups_per_batch=1,
            roots=roots,
            decision_interval=2,
            select="sampled",
            seed=0,
        )

    with build() as collector:
        next(iter(collector))
        state = copy.deepcopy(collector.state_dict())
        policy_rng = collector.policy.module.generator.get_state()
        want = [next(iter(collector)) for _ in range(3)]  # the reference: going on
        trunk_frames = collector.trunk_frames
    with build() as resumed:
        resumed.load_state_dict(state)
        resumed.policy.module.generator.set_state(policy_rng)
        got = [next(iter(resumed)) for _ in range(3)]
        assert resumed.trunk_frames == trunk_frames
    for g, w in zip(got, want, strict=True):
        assert torch.equal(g["group_id"], w["group_id"])
        assert torch.equal(g["root_step"], w["root_step"])
        assert torch.equal(g["observation"], w["observation"])
    # The control: without the state, the collector starts over.
    with build() as fresh:
        assert not torch.equal(next(iter(fresh))["group_id"], want[0]["group_id"])


def test_break_keeps_the_collector_usable_and_shutdown_closes(no_workers_left):
    env = branch_env("merge-v0", "parallel")
    collector = GroupCollector(env, RandomPolicy(), group_size=2, horizon=1, groups_per_batch=1)
    for _ in collector:
        break
    assert not env.is_closed
    assert next(iter(collector))["group_id"].unique().tolist() == [1]
    collector.shutdown()
    collector.shutdown()
    assert env.is_closed
    with pytest.raises(RuntimeError, match="shut down"):
        next(iter(collector))


@pytest.mark.slow
def test_default_spawn_workers(no_workers_left):
    # TorchRL's default start method (spawn): slow to start, checked once.
    env = make_branch_env("merge-v0", 2)
    with GroupCollector(
        env, RandomPolicy(), group_size=2, horizon=2, groups_per_batch=2, total_frames=8
    ) as collector:
        assert [int(b["mask"].sum()) for b in collector] == [8]


def test_policy_sees_branch_metadata():
    seen = []

    class Spy(ScheduledPolicy):
        def __call__(self, td):
            seen.append(td.select("group_id", "branch", "step_count").clone())
            return super().__call__(td)

    env = plain_env("merge-v0", seed=0)
    with GroupCollector(
        env, Spy(torch.ones(2, 2)), group_size=2, horizon=2, groups_per_batch=1
    ) as collector:
        next(iter(collector))
    assert [int(s["branch"][0]) for s in seen] == [0, 0, 1, 1]
    assert [int(s["step_count"][0, 0]) for s in seen] == [0, 1, 0, 1]
