"""Select-and-continue: the next root is bitwise the chosen branch's last state."""

from __future__ import annotations

import pytest
import torch
from branching_helpers import (
    N_ACTIONS,
    SCENARIOS,
    SHORT,
    ScheduledPolicy,
    actions,
    branch_env,
    plain_env,
)
from tensordict import TensorDict

from torchrl_grpo.branching import (
    branch_rollout,
    multi_turn_rollout,
    reset_roots,
    select_branches,
    shutdown_env,
)
from torchrl_grpo.envs import states_equal
from torchrl_grpo.modules import RandomPolicy


def _returns(*rows: list[float]) -> TensorDict:
    r = torch.tensor(rows).view(len(rows), -1, 1, 1)
    return TensorDict(branch_return=r, batch_size=r.shape[:3])


def test_select_best_trunk_and_sampled():
    data = _returns([1.0, 3.0, 2.0], [5.0, 5.0, -1.0])
    assert select_branches(data, "best").tolist() == [1, 0]
    assert select_branches(data, "trunk").tolist() == [0, 0]
    gen = torch.Generator().manual_seed(0)
    picks = torch.stack([select_branches(data, "sampled", generator=gen) for _ in range(400)])
    freq = torch.stack([(picks[:, 0] == g).float().mean() for g in range(3)])
    expected = torch.softmax(torch.tensor([1.0, 3.0, 2.0]), 0)
    assert torch.allclose(freq, expected, atol=0.07)
    cold = select_branches(data, "sampled", temperature=1e-3, generator=gen)
    assert cold[0].item() == 1
    with pytest.raises(ValueError, match="select must be"):
        select_branches(data, "worst")


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_continuation_is_bitwise_the_chosen_branch_final_state(scenario):
    # Episodes long enough for two turns of 2 steps.
    config = {**SHORT[scenario], "duration": 6} if SHORT[scenario] else {}
    roots = reset_roots(plain_env(scenario, seed=2, config=config), 2)
    env = branch_env(scenario, "serial", config=config)
    try:
        out = multi_turn_rollout(
            env,
            RandomPolicy(N_ACTIONS[scenario], seed=0),
            roots,
            2,
            2,
            select="sampled",
            generator=torch.Generator().manual_seed(1),
            return_states=True,
            max_turns=3,
        )
    finally:
        shutdown_env(env)
    groups = out.groups
    pairs = 0
    for e in range(2):
        rows = (out.episode == e).nonzero().squeeze(-1).tolist()
        for a, b in zip(rows, rows[1:], strict=False):
            chosen = groups[a, out.selected[a]]
            last = int(chosen["mask"].sum()) - 1
            end = chosen["next", "state"][last]
            for g in range(2):
                # "state" at t=0 of the next turn is read from the worker after the restore.
                assert states_equal(groups[b, g, 0]["state"], end), (e, a, b, g)
            assert groups[b, 0, 0]["root_step"] == groups[a, 0, 0]["root_step"] + last + 1
            pairs += 1
        assert states_equal(out.final_states[e], _last(groups[rows[-1], out.selected[rows[-1]]]))
    assert pairs >= 2
    assert torch.equal(out.groups["selected"][:, :, 0].float().argmax(1), out.selected)


def _last(branch):
    return branch["next", "state"][int(branch["mask"].sum()) - 1]


def test_multi_turn_runs_each_episode_to_its_end():
    # 4-step episodes, 3-step turns: turn 0 takes 3 steps, turn 1 ends the episode.
    scenario = "highway-fast-v0"
    config = SHORT[scenario]
    roots = reset_roots(plain_env(scenario, seed=0, config=config), 1)
    env = plain_env(scenario, config=config)
    policy = ScheduledPolicy(actions(scenario, ["IDLE"] * 3, ["FASTER"] * 3))
    out = multi_turn_rollout(env, policy, roots, 2, 3, select="best")
    assert out.turn.tolist() == [0, 1]
    assert out.ended.tolist() == [True]
    trunk = out.trunk(0)
    assert trunk.shape[0] == 4
    assert trunk["step_count"][:, 0].tolist() == [0, 1, 2, 3]
    assert trunk["next", "done"][-1].item() is True
    # "best" followed the higher-return branch in each turn.
    best = out.groups["branch_return"][:, :, 0, 0].argmax(1)
    assert torch.equal(out.selected, best)
    # The trunk equals a plain rollout of the chosen actions from the root.
    check = plain_env(scenario, config=config)
    check.set_state(roots["state"][0])
    for t in range(4):
        step = check.step(TensorDict(action=trunk["action"][t]))
        assert torch.equal(step["next", "observation"], trunk["next", "observation"][t])


def test_the_trunk_starts_at_the_root_observation():
    # Issue #20 said trunk() omits the root observation: row 0's "observation" is the
    # root's (bit for bit), and each row's observation is the previous row's next one.
    env = plain_env("merge-v0", seed=0)
    roots = reset_roots(env, 2, seed=0)
    out = multi_turn_rollout(env, RandomPolicy(seed=0), roots, 2, 2, max_turns=3)
    for e in range(2):
        trunk = out.trunk(e)
        assert trunk.shape[0] == 6
        root = roots["state", "output"][e]
        for key in ("observation", "ego_position", "speed"):
            assert torch.equal(trunk[key][0], root[key].view(torch.float32)), key
        assert torch.equal(trunk["observation"][1:], trunk["next", "observation"][:-1])
        assert trunk["step_count"][:, 0].tolist() == list(range(6))


def test_the_trunks_first_observation_is_the_envs_own_reset_observation():
    # Independent of the root's stored state: a fresh env, seeded as reset_roots seeds
    # each reset, gives the observation the trunk must start from.
    roots = reset_roots(plain_env("merge-v0"), 2, seed=3)
    out = multi_turn_rollout(plain_env("merge-v0"), RandomPolicy(seed=0), roots, 2, 2)
    seed = 3
    for e in range(2):
        fresh = plain_env("merge-v0")
        seed = fresh.set_seed(seed)  # the seed chain: root e is the reset after e seedings
        reset = fresh.reset()
        trunk = out.trunk(e)
        assert torch.equal(trunk["observation"][0], reset["observation"])
        assert torch.equal(trunk["ego_position"][0], reset["ego_position"])
        # the trunk's T + 1 observations: the reset's, then each step's next one
        observations = torch.cat([trunk["observation"][:1], trunk["next", "observation"]])
        assert observations.shape[0] == trunk.shape[0] + 1
        assert torch.equal(observations[1:-1], trunk["observation"][1:])
    other = plain_env("merge-v0")
    other.set_seed(4)  # a control: another seed's reset differs
    assert not torch.equal(out.trunk(0)["observation"][0], other.reset()["observation"])


def test_trunk_selection_follows_branch_zero():
    roots = reset_roots(plain_env("merge-v0", seed=0), 1)
    out = multi_turn_rollout(
        plain_env("merge-v0"), RandomPolicy(seed=0), roots, 3, 2, select="trunk", max_turns=2
    )
    assert out.selected.tolist() == [0, 0]
    assert out.ended.tolist() == [False]


def test_continuing_from_final_states_by_hand():
    # The user-level flow: roll out, pick a branch, continue from its end.
    from torchrl_grpo.branching import final_states, make_roots

    roots = reset_roots(plain_env("merge-v0", seed=0), 1)
    env = plain_env("merge-v0")
    data = branch_rollout(env, RandomPolicy(seed=0), roots, 3, 2, return_states=True)
    pick = select_branches(data, "best")
    nxt = make_roots(final_states(data)[0, pick], root_step=2)
    more = branch_rollout(env, RandomPolicy(seed=1), nxt, 2, 2, return_states=True)
    assert states_equal(more["state"][0, 1, 0], final_states(data)[0, pick[0]])
