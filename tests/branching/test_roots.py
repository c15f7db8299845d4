"""Root sources: episode starts, decision points along a trunk, stored trajectories."""

from __future__ import annotations

import copy

import pytest
import torch
from branching_helpers import branch_env, plain_env
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import StepCounter, TransformedEnv

from torchrl_grpo.branching import (
    StoredRoots,
    make_roots,
    reset_roots,
    roots_from_trajectories,
    shutdown_env,
    trunk_roots,
)
from torchrl_grpo.branching.root_builders import as_roots
from torchrl_grpo.branching.roots import TrunkRoots
from torchrl_grpo.envs import states_equal
from torchrl_grpo.modules import ConstantActionPolicy


def test_reset_roots_on_workers_are_distinct_episodes():
    env = branch_env("highway-fast-v0", "serial")
    try:
        env.set_seed(0)
        roots = reset_roots(env, 3)
    finally:
        shutdown_env(env)
    assert roots.batch_size == (3,) and roots["root_step"].tolist() == [0, 0, 0]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        assert not states_equal(roots["state"][i], roots["state"][j])


def test_reset_roots_are_seeded():
    a = reset_roots(plain_env("merge-v0"), 2, seed=5)
    b = reset_roots(plain_env("merge-v0"), 2, seed=5)
    # The whole state, reset output included (its reward components are seed-free).
    assert states_equal(a["state"], b["state"])
    assert not states_equal(a["state", "sim"][0], a["state", "sim"][1])


def test_trunk_roots_are_the_trunk_states_at_decision_points():
    scenario = "highway-fast-v0"
    env = plain_env(scenario)
    start = reset_roots(env, 1, seed=0)
    policy = ConstantActionPolicy("IDLE")
    roots = trunk_roots(env, policy, every=2, starts=start, max_steps=7)
    assert roots["root_step"].tolist() == [0, 2, 4, 6]
    assert roots["trunk"].tolist() == [0, 0, 0, 0]
    check = plain_env(scenario)
    check.set_state(start["state"][0])
    for step in range(7):
        if step % 2 == 0:
            assert states_equal(check.get_state(), roots["state"][step // 2]), step
        check.step(TensorDict(action=torch.tensor(1)))


def test_trunk_roots_stop_at_the_episode_end():
    env = branch_env("highway-fast-v0", "serial", config={"duration": 5})
    try:
        env.set_seed(0)
        roots = trunk_roots(env, ConstantActionPolicy("IDLE"), every=2, num_trunks=3)
    finally:
        shutdown_env(env)
    # 5-step episodes: decision points at 0, 2, 4 of each of the 3 trunks.
    assert roots["trunk"].tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert roots["root_step"].tolist() == [0, 2, 4] * 3


def test_trunk_root_source_queues_decision_points():
    env = plain_env("highway-fast-v0")
    src = TrunkRoots(every=3, max_steps=7)
    src.set_seed(0)
    first = src.next_roots(env, ConstantActionPolicy("IDLE"), 2)
    second = src.next_roots(env, ConstantActionPolicy("IDLE"), 2)
    assert first["root_step"].tolist() == [0, 3]
    assert second["root_step"].tolist() == [6, 0]
    assert src.trunk_steps >= 7


def test_roots_from_trajectories_with_return_state():
    env = plain_env("merge-v0", seed=0, return_state=True)
    data = env.rollout(5)
    roots = roots_from_trajectories(data, every=2)
    assert roots["root_step"].tolist() == [0, 2, 4]
    assert states_equal(roots["state"][0], data["state"][0])
    assert states_equal(roots["state"][1], data["next", "state"][1])
    assert states_equal(roots["state"][2], data["next", "state"][3])
    # A branch from a stored state replays the stored step exactly.
    replay = plain_env("merge-v0")
    replay.set_state(roots["state"][1])
    out = replay.step(TensorDict(action=data["action"][2]))
    assert torch.equal(out["next", "observation"], data["next", "observation"][2])


def test_roots_from_batched_trajectories_with_step_counter():
    env = TransformedEnv(plain_env("highway-fast-v0", seed=0, return_state=True), StepCounter())
    data = torch.stack([env.rollout(3), env.rollout(3)])  # [B=2, T=3]
    data["mask"] = torch.tensor([[True, True, True], [True, True, False]])
    roots = roots_from_trajectories(data, every=1)
    assert roots["root_step"].tolist() == [0, 1, 2, 3, 0, 1, 2]
    assert states_equal(roots["state"][4], data["state"][1, 0])
    assert states_equal(roots["state"][6], data["next", "state"][1, 1])
    # The state is an observation: rollout() carries each step's state to the root.
    assert states_equal(data["state"][1, 2], data["next", "state"][1, 1])


def test_roots_from_collector_trajectories_of_parallel_workers():
    # Workers built by make_branch_env return "state" through the shared buffers, so
    # TorchRL's own collector data can seed groups.
    env = branch_env("merge-v0", "parallel")
    try:
        env.set_seed(0)
        collector = Collector(env, ConstantActionPolicy("IDLE"), frames_per_batch=6, total_frames=6)
        data = next(iter(collector))
        collector.shutdown()
    finally:
        shutdown_env(env)
    assert data.batch_size == (2, 3)
    roots = roots_from_trajectories(data, every=1)
    assert roots["root_step"].tolist() == [0, 1, 2, 3, 0, 1, 2, 3]
    check = plain_env("merge-v0")
    check.set_state(roots["state"][5])
    out = check.step(TensorDict(action=data["action"][1, 1]))
    assert torch.equal(out["next", "observation"], data["next", "observation"][1, 1])


def test_as_roots_accepts_states_and_roots():
    state = plain_env("merge-v0", seed=0).get_state()
    assert as_roots(state).batch_size == (1,)
    assert as_roots([state, state]).batch_size == (2,)
    roots = make_roots(state, 4)
    assert as_roots(roots)["root_step"].tolist() == [4]


def test_stored_roots_cycle():
    roots = reset_roots(plain_env("merge-v0", seed=0), 3)
    src = StoredRoots(roots, cycle=True)
    a = src.next_roots(None, None, 2)
    b = src.next_roots(None, None, 2)
    assert states_equal(b["state"][0], roots["state"][2])
    assert states_equal(b["state"][1], a["state"][0])


def test_a_trunk_policy_given_to_the_source_drives_the_trunks():
    left, idle = ConstantActionPolicy("LANE_LEFT"), ConstantActionPolicy("IDLE")
    own = TrunkRoots(every=2, max_steps=5, policy=left)
    own.set_seed(0)
    roots = own.next_roots(plain_env("highway-fast-v0"), idle, 3)
    reference = TrunkRoots(every=2, max_steps=5)
    reference.set_seed(0)
    expected = reference.next_roots(plain_env("highway-fast-v0"), left, 3)
    assert roots["root_step"].tolist() == [0, 2, 4]
    assert states_equal(roots["state"], expected["state"])
    # The control: trunks of the collector's own policy go elsewhere.
    other = TrunkRoots(every=2, max_steps=5)
    other.set_seed(0)
    assert not states_equal(
        other.next_roots(plain_env("highway-fast-v0"), idle, 3)["state"][2], expected["state"][2]
    )


def test_a_trunk_source_continues_exactly_from_its_state_dict():
    env, idle = plain_env("highway-fast-v0"), ConstantActionPolicy("IDLE")
    src = TrunkRoots(every=3, max_steps=7)
    src.set_seed(0)
    assert src.next_roots(env, idle, 2)["root_step"].tolist() == [0, 3]  # one left queued
    state = copy.deepcopy(src.state_dict())
    assert set(state) == {"seed", "trunk_steps", "queue"}
    resumed = TrunkRoots(every=3, max_steps=7)
    resumed.load_state_dict(state)
    want = src.next_roots(env, idle, 4)  # the reference: the source itself, going on
    got = resumed.next_roots(plain_env("highway-fast-v0"), idle, 4)
    assert got["root_step"].tolist() == want["root_step"].tolist() == [6, 0, 3, 6]
    assert states_equal(got["state"], want["state"])
    assert (resumed.trunk_steps, resumed.seed) == (src.trunk_steps, src.seed)
    # The control: a fresh source with the same seed starts over.
    fresh = TrunkRoots(every=3, max_steps=7)
    fresh.set_seed(0)
    assert fresh.next_roots(env, idle, 1)["root_step"].tolist() == [0]


def test_a_partial_state_dict_leaves_the_rest_of_the_source_as_it_is():
    env = plain_env("highway-fast-v0")
    src = TrunkRoots(every=3, max_steps=7)
    src.set_seed(0)
    src.next_roots(env, ConstantActionPolicy("IDLE"), 2)
    before = copy.deepcopy(src.state_dict())
    src.load_state_dict({})  # a state saved before the source recorded anything
    src.load_state_dict({"trunk_steps": 2})
    after = src.state_dict()
    assert after["trunk_steps"] == 2
    assert after["seed"] == before["seed"]
    assert torch.equal(after["queue"]["root_step"], before["queue"]["root_step"])


def test_stored_roots_state_dict_holds_the_read_position():
    roots = reset_roots(plain_env("merge-v0", seed=0), 3)
    src = StoredRoots(roots)
    src.next_roots(None, None, 2)
    resumed = StoredRoots(roots)
    resumed.load_state_dict(src.state_dict())
    assert src.state_dict() == {"seed": None, "pos": 2}
    assert states_equal(resumed.next_roots(None, None, 2)["state"], roots["state"][2:])


def seeded(*sources: TrunkRoots) -> tuple[TrunkRoots, ...]:
    """The sources, each seeded alike: their trunks start from the same episodes."""
    for source in sources:
        source.set_seed(3)
    return sources


def test_staggered_live_trunks_start_spread_over_the_episode():
    env, slower = plain_env("highway-fast-v0"), ConstantActionPolicy("SLOWER")
    staggered, together = seeded(
        TrunkRoots(every=2, live=True, stagger=8), TrunkRoots(every=2, live=True)
    )
    first = staggered.next_roots(env, slower, 4)
    # Trunk i runs i * 8 // 4 steps, in whole segments of 2: 0, 2, 4, 6.
    assert first["root_step"].tolist() == [0, 2, 4, 6]
    assert staggered.trunk_steps == 12
    # Each is the state its own episode reaches after those steps: the trunks that start
    # together, advanced segment by segment, pass through the same states.
    seen = [together.next_roots(env, slower, 4) for _ in range(4)]
    for i in range(4):
        assert seen[i]["root_step"][i].item() == 2 * i
        assert states_equal(first["state"][i], seen[i]["state"][i])
    assert not states_equal(first["state"][1], seen[0]["state"][1])
    # After the spread every live trunk advances one segment per batch.
    assert staggered.next_roots(env, slower, 4)["root_step"].tolist() == [2, 4, 6, 8]


def test_trunks_take_decision_points_from_their_first_root_step():
    env, slower = plain_env("highway-fast-v0"), ConstantActionPolicy("SLOWER")
    late, together = seeded(
        TrunkRoots(every=2, live=True, min_steps=3), TrunkRoots(every=1, live=True)
    )
    first = late.next_roots(env, slower, 2)
    assert first["root_step"].tolist() == [3, 3] and late.trunk_steps == 6
    for _ in range(4):
        seen = together.next_roots(env, slower, 2)
    assert seen["root_step"].tolist() == [3, 3]
    for i in range(2):
        assert states_equal(first["state"][i], seen["state"][i])
    assert late.next_roots(env, slower, 2)["root_step"].tolist() == [5, 5]
    # Queued trunks drop the decision points before it.
    queued = TrunkRoots(every=2, max_steps=7, min_steps=3)
    queued.set_seed(0)
    assert queued.next_roots(env, slower, 2)["root_step"].tolist() == [4, 6]


def test_a_negative_stagger_or_an_empty_step_range_is_refused():
    with pytest.raises(ValueError, match="stagger must be >= 0, got -1"):
        TrunkRoots(every=1, live=True, stagger=-1)
    with pytest.raises(ValueError, match=r"below max_steps \(4\), got 4"):
        TrunkRoots(every=1, max_steps=4, min_steps=4)
