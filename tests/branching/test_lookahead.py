"""LookaheadPolicy: every action from the current state, then a base policy; the best wins."""

from __future__ import annotations

import pytest
import torch
from branching_helpers import plain_env
from tensordict import TensorDict

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import TensorHighwayEnv, states_equal
from torchrl_grpo.modules import ConstantActionPolicy, make_scripted_policy

SCENARIO = "highway-fast-v0"


def _branch(state, first: int, base_action: int, horizon: int) -> tuple[float, int]:
    """A branch's return and length computed independently: restore, step, sum."""
    env = plain_env(SCENARIO)
    env.set_state(state)
    total, steps = 0.0, 0
    for t in range(horizon):
        out = env.step(TensorDict(action=torch.tensor(first if t == 0 else base_action)))
        total += float(out["next", "reward"])
        steps += 1
        if bool(out["next", "done"]):
            break
    return total, steps


def test_the_planned_action_is_the_best_branch_and_the_driven_env_is_untouched():
    env = plain_env(SCENARIO, seed=3, return_state=True)
    td = env.rollout(4, ConstantActionPolicy("FASTER"))[-1]["next"].clone()
    before = env.get_state()
    planner = LookaheadPolicy(plain_env(SCENARIO), ConstantActionPolicy("IDLE"), horizon=3)
    scores = planner.returns(td)
    branches = [_branch(td["state"], a, 1, 3) for a in range(5)]
    expected = [total for total, _ in branches]
    assert scores.tolist() == expected
    assert len(set(expected)) > 1  # the control: the actions do differ here
    assert int(planner(td.clone())["action"]) == max(range(5), key=lambda a: (expected[a], -a))
    assert planner.frames == 2 * sum(steps for _, steps in branches)
    assert states_equal(env.get_state(), before)


def test_batched_input_is_planned_row_by_row():
    env = plain_env(SCENARIO, seed=0, return_state=True)
    rows = env.rollout(3, ConstantActionPolicy("SLOWER"))["next"]
    planner = LookaheadPolicy(plain_env(SCENARIO), ConstantActionPolicy("SLOWER"), horizon=2)
    batched = planner(rows.clone())["action"]
    one_by_one = [int(planner(rows[i].clone())["action"]) for i in range(3)]
    assert batched.tolist() == one_by_one


def test_bad_input_names_the_problem():
    planner = LookaheadPolicy(plain_env(SCENARIO), ConstantActionPolicy("IDLE"), horizon=2)
    env = plain_env(SCENARIO, seed=0)
    first = env.step(env.reset().set("action", torch.tensor(1)))["next"]
    with pytest.raises(KeyError, match="return_state=True"):
        planner(first)
    # Without return_state a rollout carries the reset's state to every step: refused.
    stale = env.rollout(3, ConstantActionPolicy("IDLE"))[-1]
    assert "state" in stale.keys()
    with pytest.raises(ValueError, match="stale state"):
        planner(stale)
    with pytest.raises(ValueError, match="horizon"):
        LookaheadPolicy(plain_env(SCENARIO), ConstantActionPolicy("IDLE"), horizon=0)


def test_on_batched_worlds_all_rows_are_planned_in_one_rollout_as_row_by_row():
    env = TensorHighwayEnv(SCENARIO, num_envs=6, seed=0, return_state=True, dtype=torch.float64)
    td = env.reset()
    rule = make_scripted_policy("rule")
    plan_env = TensorHighwayEnv(SCENARIO, num_envs=12, seed=1, dtype=torch.float64)
    planner = LookaheadPolicy(plan_env, rule, horizon=4)
    scores = planner.returns(td)
    assert scores.shape == (6, 5)
    # Each row alone (its 5 branches in one wave) scores the same.
    for i in range(6):
        assert torch.equal(planner.returns(td[i]), scores[i])
    # Batched: N x 5 = 30 branches in waves of 12 rows, each row's best action.
    actions = planner(td.clone())["action"]
    assert torch.equal(actions, scores.argmax(-1))
    assert len(set(scores.flatten().tolist())) > 1  # the control: the actions differ


def test_a_stale_tensor_state_carried_from_the_reset_is_refused():
    env = TensorHighwayEnv(SCENARIO, num_envs=3, seed=0)  # no return_state
    data = env.rollout(2, ConstantActionPolicy("IDLE"))
    planner = LookaheadPolicy(
        TensorHighwayEnv(SCENARIO, num_envs=15), ConstantActionPolicy("IDLE"), 2
    )
    planner.returns(data[:, 0])  # the reset's own state: fresh
    with pytest.raises(ValueError, match="return_state=True"):
        planner.returns(data[:, 1])  # the reset's state, carried to the next step


def test_env_rollout_with_auto_reset_plans_the_reset_worlds_from_their_new_state():
    # The rows that end are reset by the rollout; the planner must read their new state
    env = TensorHighwayEnv(SCENARIO, num_envs=3, seed=0, return_state=True)
    planner = LookaheadPolicy(
        TensorHighwayEnv(SCENARIO, num_envs=15), make_scripted_policy("aggressive"), 1
    )
    data = env.rollout(40, planner, break_when_any_done=False)
    done = data["next", "done"].squeeze(-1)
    row, t = done[:, :-1].nonzero()[0].tolist()  # a row reset inside the rollout
    after = data[row, t + 1]
    assert int(after["state", "steps"]) == 0  # a fresh episode's first step
    assert int(after["action"]) == int(planner.returns(after).argmax())


def test_planning_on_the_tensor_simulator_for_highway_env_scores_as_its_snapshots():
    # The driven env is highway-env; one planner branches on its snapshots, the other on
    # the tensor simulator from the same states imported through the bridge.
    env = plain_env(SCENARIO, seed=7, return_state=True)
    rows = env.rollout(6, make_scripted_policy("rule"))["next"]
    before = env.get_state()
    rule = make_scripted_policy("rule")
    on_highway = LookaheadPolicy(plain_env(SCENARIO), rule, horizon=3)
    sim = TensorHighwayEnv(SCENARIO, num_envs=5, dtype=torch.float64)
    on_tensor = LookaheadPolicy(sim, rule, horizon=3, import_state=sim.state_from_highway)
    expected = torch.stack([on_highway.returns(rows[i]) for i in range(6)])
    scores = torch.stack([on_tensor.returns(rows[i]) for i in range(6)])
    # Equal up to the rounding of highway-env's float32 rewards.
    torch.testing.assert_close(scores, expected, rtol=0, atol=1e-5)
    assert len(set(expected.flatten().tolist())) > 1  # the control: the actions differ
    assert on_tensor.frames == on_highway.frames
    for i in range(6):
        assert int(on_tensor(rows[i].clone())["action"]) == int(expected[i].argmax())
    assert states_equal(env.get_state(), before)
