"""branch_rollout: shared starts, identical branches, backends agree, masks, metadata."""

from __future__ import annotations

import pytest
import torch
from branching_helpers import (
    N_ACTIONS,
    SCENARIOS,
    SHORT,
    ScheduledPolicy,
    actions,
    bitwise_equal,
    branch_env,
    plain_env,
)
from tensordict import TensorDict
from torchrl.objectives.llm import MCAdvantage

from torchrl_grpo.branching import (
    branch_rollout,
    final_states,
    make_roots,
    reset_roots,
    shutdown_env,
)
from torchrl_grpo.branching.seeding import branch_seed
from torchrl_grpo.envs import states_equal
from torchrl_grpo.modules import KinematicsMLP, RandomPolicy, make_discrete_actor
from torchrl_grpo.objectives import GroupRelativeAdvantage

IDLE, FASTER, LANE_LEFT, LANE_RIGHT, SLOWER = 1, 3, 0, 2, 4


def _roots(scenario: str, n: int, seed: int = 0, **kwargs):
    env = plain_env(scenario, seed=seed, **kwargs)
    return reset_roots(env, n)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_every_branch_starts_from_bitwise_the_same_state(scenario):
    roots = _roots(scenario, 2)
    env = branch_env(scenario, "serial")
    try:
        data = branch_rollout(
            env, RandomPolicy(N_ACTIONS[scenario]), roots, 3, 2, return_states=True
        )
    finally:
        shutdown_env(env)
    check = plain_env(scenario)
    for r in range(2):
        restored = check.set_state(roots["state"][r])
        for g in range(3):
            # "state" at t=0 is read back from the worker after the restore.
            assert states_equal(data["state"][r, g, 0], roots["state"][r]), (r, g)
            assert torch.equal(data["observation"][r, g, 0], restored["observation"])
    # The two roots are different episodes: the test would see a root mix-up.
    assert not states_equal(roots["state"][0], roots["state"][1])


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_identical_actions_give_identical_branches(scenario):
    roots = _roots(scenario, 1)
    table = actions(scenario, ["FASTER", "IDLE", "LANE_LEFT", "SLOWER"]).expand(3, 4)
    env = branch_env(scenario, "serial")
    try:
        data = branch_rollout(env, ScheduledPolicy(table), roots, 3, 4, return_states=True)
    finally:
        shutdown_env(env)
    data = data.exclude("branch", ("collector", "traj_ids"))
    for g in (1, 2):
        assert bitwise_equal(data[0, 0], data[0, g]) == [], g


def test_different_actions_give_different_branches():
    roots = _roots("highway-fast-v0", 1)
    table = torch.tensor([[IDLE] * 3, [LANE_LEFT] * 3])
    env = plain_env("highway-fast-v0")
    data = branch_rollout(env, ScheduledPolicy(table), roots, 2, 3, return_states=True)
    assert not torch.equal(data["next", "ego_position"][0, 0], data["next", "ego_position"][0, 1])


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_serial_parallel_and_single_env_agree(scenario):
    # R * G = 6 branches on 2 workers: three waves, the second mixing both roots, and a
    # different branch-to-worker mapping than the single env's. Per-branch actions
    # differ, so a mix-up of states or actions would show.
    roots = _roots(scenario, 2)
    table = actions(scenario, ["FASTER", "LANE_LEFT"], ["SLOWER", "LANE_RIGHT"], ["IDLE", "FASTER"])
    results = {}
    for backend in ("single", "serial", "parallel"):
        env = branch_env(scenario, backend)
        try:
            results[backend] = branch_rollout(
                env, ScheduledPolicy(table), roots, 3, 2, return_states=True
            )
        finally:
            shutdown_env(env)
    assert results["single"]["mask"].any()
    assert bitwise_equal(results["single"], results["serial"]) == []
    assert bitwise_equal(results["single"], results["parallel"]) == []


@pytest.mark.parametrize("backend", ["single", "parallel"])
def test_masks_across_episode_ends(backend):
    # Episodes of 4 steps; root 1 is 2 steps in, so its branches end after 2 steps,
    # root 0's after 4, within a horizon of 6.
    scenario, config = "highway-fast-v0", SHORT["highway-fast-v0"]
    env0 = plain_env(scenario, seed=3, config=config)
    env0.reset()
    start = env0.get_state()
    idle = TensorDict(action=torch.tensor(IDLE))
    expected = []
    for _ in range(4):
        expected.append(env0.step(idle.clone())["next"].clone())
    env0.set_state(start)
    env0.step(idle.clone())
    env0.step(idle.clone())
    later = env0.get_state()
    roots = make_roots([start, later], torch.tensor([0, 2]))
    env = branch_env(scenario, backend, config=config)
    try:
        data = branch_rollout(env, ScheduledPolicy(torch.full((2, 6), IDLE)), roots, 2, 6)
    finally:
        shutdown_env(env)
    mask = data["mask"]
    assert mask[0].tolist() == [[True] * 4 + [False] * 2] * 2
    assert mask[1].tolist() == [[True] * 2 + [False] * 4] * 2
    # Valid steps are the env's own episode, step for step: no auto-reset leaked in.
    for t in range(4):
        assert torch.equal(data["next", "observation"][0, 0, t], expected[t]["observation"])
    for t in range(2):
        assert torch.equal(data["next", "observation"][1, 1, t], expected[t + 2]["observation"])
    assert data["next", "truncated"][0, :, 3].all() and data["next", "done"][1, :, 1].all()
    # After the end: zeros, never a new episode.
    assert (data["next", "observation"][~mask] == 0).all()
    assert not data["next", "done"][~mask].any()
    assert (data["next", "reward"][~mask] == 0).all()
    returns = (data["next", "reward"] * mask.unsqueeze(-1)).sum(2)
    assert torch.equal(data["branch_return"][:, :, 0], returns)
    assert data["step_count"][1, 0, :, 0].tolist() == [2, 3, 4, 5, 6, 7]


def test_horizon_cut_is_flagged_only_with_set_truncated():
    roots = _roots("merge-v0", 1)
    env = plain_env("merge-v0")
    policy = ScheduledPolicy(torch.full((2, 3), IDLE))
    flagged = branch_rollout(env, policy, roots, 2, 3)
    plain = branch_rollout(env, policy, roots, 2, 3, set_truncated=False)
    assert flagged["next", "truncated"][0, :, 2].all() and flagged["next", "done"][0, :, 2].all()
    assert not plain["next", "done"].any()
    assert flagged["next", "done"][0, :, :2].any().item() is False


def test_metadata_and_group_ids():
    roots = make_roots(_roots("merge-v0", 2)["state"], torch.tensor([0, 5]))
    env = plain_env("merge-v0")
    data = branch_rollout(env, RandomPolicy(), roots, 3, 2, first_group_id=40)
    assert data["group_id"].dtype == torch.int64 and data["group_id"].shape == (2, 3, 2)
    assert data["group_id"][:, :, :].unique(sorted=True).tolist() == [40, 41]
    assert (data["group_id"][1] == 41).all()
    assert data["branch"][0, :, 0].tolist() == [0, 1, 2]
    assert data["root_step"][1].unique().tolist() == [5]
    assert data["step_count"][1, 2, :, 0].tolist() == [5, 6]
    assert data["collector", "traj_ids"][:, :, 0].flatten().unique().numel() == 6
    assert data["mask"].dtype == torch.bool


def test_final_states_continue_the_branch():
    roots = _roots("highway-fast-v0", 1)
    table = torch.tensor([[FASTER, IDLE, LANE_LEFT], [IDLE, IDLE, IDLE]])
    env = plain_env("highway-fast-v0")
    data = branch_rollout(env, ScheduledPolicy(table), roots, 2, 3, return_states=True)
    last = final_states(data)
    check = plain_env("highway-fast-v0")
    for g in range(2):
        check.set_state(roots["state"][0])
        for t in range(3):
            check.step(TensorDict(action=table[g, t]))
        assert states_equal(check.get_state(), last[0, g])


def test_policy_log_prob_and_advantages():
    # The GRPO objective reads the actor's log-prob key and the group layout.
    roots = _roots("merge-v0", 2)
    env = plain_env("merge-v0")
    actor = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
    data = branch_rollout(env, actor, roots, 3, 3)
    assert actor.log_prob_keys == ["action_log_prob"]
    assert data["action_log_prob"].shape == (2, 3, 3)
    adv = GroupRelativeAdvantage()(data.clone())["advantage"]
    assert adv.shape == (2, 3, 3, 1)
    assert torch.allclose(adv.sum(1), torch.zeros(2, 3, 1), atol=1e-5)
    # MCAdvantage groups the flattened valid steps by group_id.
    mc = MCAdvantage(grpo_size=3, prompt_key="group_id", trajectory_return="sum")
    out = mc.inv(data[0][data[0]["mask"]])
    assert out is not None and out["advantage"].shape[0] == int(data[0]["mask"].sum())


def test_per_branch_rng_diversifies_intersection_traffic():
    scenario = "intersection-v0"
    roots = _roots(scenario, 1, seed=1)
    env = plain_env(scenario)
    policy = ScheduledPolicy(torch.full((3, 6), IDLE))
    shared = branch_rollout(env, policy, roots, 3, 6, return_states=True)
    reseeded = branch_rollout(
        env, policy, roots, 3, 6, return_states=True, rng="per_branch", seed=7
    )
    other = lambda d, g: d["next", "state", "sim", "entities"][0, g]  # noqa: E731
    assert bitwise_equal(other(shared, 0), other(shared, 1)) == []
    assert bitwise_equal(other(reseeded, 0), other(reseeded, 1)) != []
    # Same seed, same branch: the reseeded branches are reproducible.
    again = branch_rollout(env, policy, roots, 3, 6, return_states=True, rng="per_branch", seed=7)
    assert bitwise_equal(reseeded, again) == []
    # Each branch starts from its root reseeded by the env with its branch seed.
    for g in range(3):
        expected = env.reseed_state(roots["state"][0], branch_seed(7, 0, g))
        assert states_equal(reseeded["state"][0, g, 0], expected), g


@pytest.mark.parametrize("backend", ["serial", "parallel"])
def test_per_branch_rng_on_workers_matches_the_plain_env(backend):
    # Batched envs reseed through one call to their first worker: same states as in process.
    scenario = "intersection-v0"
    roots = _roots(scenario, 2, seed=1)
    policy = ScheduledPolicy(torch.full((2, 4), IDLE))
    kwargs = {"return_states": True, "rng": "per_branch", "seed": 3, "first_group_id": 5}
    env = branch_env(scenario, backend)
    try:
        parallel = branch_rollout(env, policy, roots, 2, 4, **kwargs)
    finally:
        shutdown_env(env)
    single = branch_rollout(plain_env(scenario), policy, roots, 2, 4, **kwargs)
    assert bitwise_equal(parallel, single) == []
    assert not states_equal(parallel["state"][0, 0, 0], parallel["state"][0, 1, 0])


def test_states_without_state_outputs_are_read_from_workers():
    # snapshots=False: workers do not return states; they come back through
    # env.get_state() on every worker.
    roots = _roots("merge-v0", 2)
    table = actions("merge-v0", ["FASTER", "IDLE"], ["LANE_LEFT", "SLOWER"])
    env = branch_env("merge-v0", "parallel", snapshots=False)
    assert "state" not in env.observation_spec.keys()
    try:
        slow = branch_rollout(env, ScheduledPolicy(table), roots, 2, 2, return_states=True)
    finally:
        shutdown_env(env)
    fast = branch_rollout(
        plain_env("merge-v0"), ScheduledPolicy(table), roots, 2, 2, return_states=True
    )
    assert bitwise_equal(slow, fast) == []
