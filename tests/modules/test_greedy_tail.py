"""GreedyTail: sampled actions at the start of each branch, greedy actions after."""

from __future__ import annotations

from contextlib import nullcontext
from unittest.mock import patch

import pytest
import torch
from modules_helpers import Counted
from tensordict import TensorDict
from torchrl.data import Categorical
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching import branch_rollout, reset_roots
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import (
    ConstantActionPolicy,
    CrashHead,
    GreedyTail,
    greedy_tail,
    make_discrete_actor,
)
from torchrl_grpo.modules.greedy_tail import EXPLORED
from torchrl_grpo.modules.scripted.actions import SLOWER

N_ACTIONS = 5


def _actor(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return make_discrete_actor(torch.nn.Linear(4, N_ACTIONS), Categorical(N_ACTIONS))


def _enumerated_then_slower(actor: torch.nn.Module, learner_steps: int) -> GreedyTail:
    """Every first action enumerated, the learner's greedy steps, then always-SLOWER."""
    return GreedyTail(
        actor,
        explore_steps=1,
        first_action="enumerate",
        tail_policy=ConstantActionPolicy("SLOWER"),
        learner_steps=learner_steps,
    )


def _rows(n: int, t: list[int]) -> TensorDict:
    return TensorDict(
        observation=torch.randn(n, 4),
        root_step=torch.full((n,), 10),
        step_count=torch.tensor(t).unsqueeze(-1) + 10,
        batch_size=[n],
    )


def test_rows_past_explore_steps_take_the_argmax_and_are_not_explored():
    actor = _actor()
    td = _rows(6, [0, 1, 2, 3, 4, 5])
    out = GreedyTail(actor, explore_steps=2)(td.clone())
    assert out[EXPLORED].tolist() == [True, True, False, False, False, False]
    argmax = actor.module[0](td)["logits"].argmax(-1)  # the logits network, independently
    assert torch.equal(out["action"][2:], argmax[2:])


def test_explored_rows_are_sampled_like_the_policy_itself():
    # Same generator state, same rows: the explored rows equal the wrapped policy's samples.
    actor = _actor()
    td = _rows(64, [0] * 32 + [9] * 32)
    torch.manual_seed(3)
    ours = GreedyTail(actor, explore_steps=1)(td.clone())
    torch.manual_seed(3)
    plain = actor(td.clone())
    assert torch.equal(ours["action"][:32], plain["action"][:32])
    assert torch.equal(ours["action_log_prob"][:32], plain["action_log_prob"][:32])
    # The sampled half is not all greedy (a random linear layer is far from peaked).
    assert not torch.equal(ours["action"][:32], actor.module[0](td)["logits"][:32].argmax(-1))


def test_deterministic_mode_is_greedy_everywhere():
    actor = _actor()
    td = _rows(4, [0, 0, 1, 2])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = GreedyTail(actor, explore_steps=5)(td.clone())
    assert not out[EXPLORED].any()
    assert torch.equal(out["action"], actor.module[0](td)["logits"].argmax(-1))


def test_needs_branch_steps_and_a_positive_int():
    actor = _actor()
    with pytest.raises(KeyError, match="root_step"):
        GreedyTail(actor, 1)(TensorDict(observation=torch.randn(2, 4), batch_size=[2]))
    with pytest.raises(ValueError, match="explore_steps must be >= 1"):
        GreedyTail(actor, 0)
    with pytest.raises(TypeError, match="explore_steps must be an int"):
        GreedyTail(actor, 1.5)


def _env_actor(scenario: str) -> tuple[HighwayEnv, torch.nn.Module]:
    """An env and a linear actor over its flattened kinematics table."""
    env = HighwayEnv(scenario, seed=0)
    obs_dim = env.observation_spec["observation"].shape.numel()
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Flatten(-2), torch.nn.Linear(obs_dim, N_ACTIONS))
    return env, make_discrete_actor(net, env.action_spec)


def test_branch_rollout_marks_the_first_steps_of_every_branch():
    env, actor = _env_actor("merge-v0")
    roots = reset_roots(env, 1, seed=0)
    out = branch_rollout(env, GreedyTail(actor, explore_steps=2), roots, group_size=3, horizon=4)
    explored = out[EXPLORED] & out["mask"]
    assert explored[..., :2].all() and not explored[..., 2:].any()
    env.close()


def test_enumerated_first_actions_cover_every_action_with_their_own_log_prob():
    actor = _actor()
    td = _rows(2 * N_ACTIONS + 1, [0] * (2 * N_ACTIONS) + [1])
    td["branch"] = torch.arange(2 * N_ACTIONS + 1)
    out = GreedyTail(actor, explore_steps=1, first_action="enumerate")(td.clone())
    first = 2 * N_ACTIONS
    assert out["action"][:first].tolist() == list(range(N_ACTIONS)) * 2
    # The log-prob is the policy's own, computed independently from the logits.
    logits = actor.module[0](td)["logits"]
    expected = torch.log_softmax(logits, -1).gather(-1, out["action"].unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(out["action_log_prob"][:first], expected[:first])
    # The step after the first is greedy and not explored.
    assert out["action"][first] == logits[first].argmax()
    assert out[EXPLORED].tolist() == [True] * first + [False]


def test_enumerated_one_hot_actions():
    torch.manual_seed(0)
    from torchrl.data import OneHot

    actor = make_discrete_actor(torch.nn.Linear(4, 3), OneHot(3))
    td = _rows(3, [0, 0, 0])
    td["branch"] = torch.arange(3)
    out = GreedyTail(actor, explore_steps=1, first_action="enumerate")(td)
    assert torch.equal(out["action"], torch.eye(3, dtype=out["action"].dtype))


def test_enumerate_needs_the_branch_index_and_a_probabilistic_actor():
    actor = _actor()
    with pytest.raises(KeyError, match="branch"):
        GreedyTail(actor, 1, first_action="enumerate")(_rows(2, [0, 0]))
    with pytest.raises(ValueError, match="first_action must be"):
        GreedyTail(actor, 1, first_action="all")
    with pytest.raises(TypeError, match="probabilistic actor"):
        GreedyTail(actor.module[0], 1, first_action="enumerate")


def test_enumerated_groups_branch_every_action_from_one_root():
    env, actor = _env_actor("highway-fast-v0")
    roots = reset_roots(env, 1, seed=0)
    policy = GreedyTail(actor, explore_steps=1, first_action="enumerate")
    out = branch_rollout(env, policy, roots, group_size=N_ACTIONS, horizon=3)
    assert out["action"][0, :, 0].tolist() == list(range(N_ACTIONS))
    # After the first step every branch follows the greedy policy of its own observation.
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = actor(out[0, :, 1].select("observation").clone())["action"]
    assert torch.equal(out["action"][0, :, 1], greedy)
    env.close()


def test_a_tail_policy_takes_the_greedy_steps_and_the_deterministic_mode():
    actor, tail = _actor(0), _actor(1)
    td = _rows(6, [0, 0, 0, 1, 2, 3])
    out = GreedyTail(actor, explore_steps=1, tail_policy=tail)(td.clone())
    tail_argmax = tail.module[0](td)["logits"].argmax(-1)
    assert torch.equal(out["action"][3:], tail_argmax[3:])
    # The control: the two actors disagree on some of these rows.
    assert not torch.equal(tail_argmax, actor.module[0](td)["logits"].argmax(-1))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = GreedyTail(actor, explore_steps=1, tail_policy=tail)(td.clone())
    assert torch.equal(greedy["action"], tail_argmax)


def test_a_scripted_tail_acts_after_the_enumerated_first_action():
    env, actor = _env_actor("highway-fast-v0")
    roots = reset_roots(env, 1, seed=0)
    policy = GreedyTail(
        actor, explore_steps=1, first_action="enumerate", tail_policy=ConstantActionPolicy("SLOWER")
    )
    out = branch_rollout(env, policy, roots, group_size=N_ACTIONS, horizon=3)[0]
    env.close()
    assert out["action"][:, 0].tolist() == list(range(N_ACTIONS))
    tail = out["mask"][:, 1:]
    assert bool(tail.any())
    assert (out["action"][:, 1:][tail] == SLOWER).all()
    assert not out[EXPLORED][:, 1:][tail].any()
    # The explored steps keep the learner's own log-prob of the enumerated action.
    logits = actor.module[0](out[:, 0].select("observation").clone())["logits"]
    expected = torch.log_softmax(logits, -1)[torch.arange(N_ACTIONS), torch.arange(N_ACTIONS)]
    torch.testing.assert_close(out["action_log_prob"][:, 0], expected)


def test_learner_steps_come_between_the_explored_step_and_a_scripted_tail():
    actor, tail = _actor(0), _actor(1)
    td = _rows(8, [0, 1, 2, 3, 4, 0, 1, 5])
    out = GreedyTail(actor, explore_steps=1, tail_policy=tail, learner_steps=2)(td.clone())
    argmax = actor.module[0](td)["logits"].argmax(-1)
    tail_argmax = tail.module[0](td)["logits"].argmax(-1)
    learner_rows, tail_rows = [1, 2, 6], [3, 4, 7]
    assert torch.equal(out["action"][learner_rows], argmax[learner_rows])
    assert torch.equal(out["action"][tail_rows], tail_argmax[tail_rows])
    # The control: the two actors disagree on some of these rows.
    assert not torch.equal(argmax[1:5], tail_argmax[1:5])
    assert out[EXPLORED].tolist() == [True, False, False, False, False, True, False, False]


def test_learner_steps_in_a_branch_rollout_then_the_scripted_tail():
    env, actor = _env_actor("highway-fast-v0")
    roots = reset_roots(env, 1, seed=0)
    policy = _enumerated_then_slower(actor, learner_steps=1)
    out = branch_rollout(env, policy, roots, group_size=N_ACTIONS, horizon=4)[0]
    env.close()
    assert out["action"][:, 0].tolist() == list(range(N_ACTIONS))
    second = out[:, 1][out["mask"][:, 1]]
    greedy = actor.module[0](second.select("observation").clone())["logits"].argmax(-1)
    assert torch.equal(second["action"], greedy)
    tail = out["mask"][:, 2:]
    assert (out["action"][:, 2:][tail] == SLOWER).all()


def test_learner_branches_leave_the_later_branches_to_the_scripted_tail():
    # Every action twice: branches 0..n-1 follow the learner for 2 steps, n..2n-1 brake.
    env, actor = _env_actor("highway-fast-v0")
    roots = reset_roots(env, 1, seed=0)
    policy = GreedyTail(
        actor,
        explore_steps=1,
        first_action="enumerate",
        tail_policy=ConstantActionPolicy("SLOWER"),
        learner_steps=2,
        learner_branches=N_ACTIONS,
    )
    out = branch_rollout(env, policy, roots, group_size=2 * N_ACTIONS, horizon=4)[0]
    env.close()
    assert out["action"][:, 0].tolist() == 2 * list(range(N_ACTIONS))
    learner = out[:N_ACTIONS, 1][out["mask"][:N_ACTIONS, 1]]
    greedy = actor.module[0](learner.select("observation").clone())["logits"].argmax(-1)
    assert torch.equal(learner["action"], greedy)
    assert not (greedy == SLOWER).all()  # the control: the learner would not brake everywhere
    base = out["mask"][N_ACTIONS:, 1:]
    assert (out["action"][N_ACTIONS:, 1:][base] == SLOWER).all()
    # Identical first actions from one root: until the learner acts, the halves agree.
    assert torch.equal(out["observation"][:N_ACTIONS, 1], out["observation"][N_ACTIONS:, 1])


def test_learner_branches_need_enumerated_first_actions_and_learner_steps():
    actor = _actor()
    with pytest.raises(ValueError, match="learner_branches=5 splits"):
        GreedyTail(
            actor, explore_steps=1, tail_policy=_actor(1), learner_steps=2, learner_branches=5
        )
    with pytest.raises(ValueError, match="learner_steps >= 1, got 'enumerate' and 0"):
        GreedyTail(
            actor,
            explore_steps=1,
            first_action="enumerate",
            tail_policy=_actor(1),
            learner_branches=5,
        )


def test_learner_steps_need_a_tail_policy_and_a_non_negative_int():
    actor = _actor()
    with pytest.raises(ValueError, match="only with a tail_policy"):
        GreedyTail(actor, explore_steps=1, learner_steps=2)
    with pytest.raises(ValueError, match="must be >= 0"):
        GreedyTail(actor, explore_steps=1, tail_policy=_actor(1), learner_steps=-1)
    with pytest.raises(TypeError, match="learner_steps must be an int"):
        GreedyTail(actor, explore_steps=1, tail_policy=_actor(1), learner_steps=1.0)


def test_the_sampled_and_greedy_outputs_share_one_forward_and_keep_their_values():
    # experiment=drive's rollout policy: a crash head, a scripted tail, learner steps.
    torch.manual_seed(0)
    net = Counted(25, 2 * N_ACTIONS)
    head = CrashHead(torch.nn.Sequential(torch.nn.Flatten(-2), net), N_ACTIONS, aversion=3.0)
    actor = make_discrete_actor(head, Categorical(N_ACTIONS))
    td = _rows(8, [0, 1, 2, 3, 4, 0, 1, 5])
    td["observation"] = torch.randn(8, 5, 5)  # a Kinematics table, as the scripted tail reads
    td["branch"] = torch.arange(8)
    policy = _enumerated_then_slower(actor, learner_steps=3)
    with torch.no_grad():
        torch.manual_seed(1)
        out = policy(td.clone())
        assert net.runs == 1
        # The reference: the same calls without the shared forward (its network runs twice).
        torch.manual_seed(1)
        with patch.object(greedy_tail, "shared_forward", lambda *a, **k: nullcontext()):
            alone = policy(td.clone())
        assert net.runs == 3
    assert (out == alone).all()
    logits = actor.module[0](td)["logits"]
    learner_rows, tail_rows = [1, 2, 3, 6], [4, 7]
    assert torch.equal(out["action"][learner_rows], logits[learner_rows].argmax(-1))
    assert (out["action"][tail_rows] == SLOWER).all()  # past the learner's steps


class _NoKeys(torch.nn.Module):
    """The tail without ``out_keys``: GreedyTail cannot tell what it writes, so it runs it."""

    def __init__(self, tail: torch.nn.Module) -> None:
        super().__init__()
        self.tail = tail

    def forward(self, td: TensorDict) -> TensorDict:
        return self.tail(td)


@pytest.mark.parametrize("t", [[1, 2, 3, 1, 2, 3], [0, 1, 2, 3, 0, 2]])
def test_a_tail_with_nothing_to_act_on_is_not_run_and_changes_nothing(t):
    # The recipe's branches end within the learner's steps: every greedy row is the
    # learner's. The output must be what running the tail gives, key by key, bitwise.
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Flatten(-2), torch.nn.Linear(20, N_ACTIONS))
    actor = make_discrete_actor(net, Categorical(N_ACTIONS))
    tail = ConstantActionPolicy("SLOWER")
    td = _rows(6, t)
    td["observation"] = torch.randn(6, 5, 4)
    td["branch"] = torch.arange(6)
    # The keys a rollout step carries over from the step before (step_mdp keep_other).
    td["logits"], td["action_log_prob"] = torch.randn(6, N_ACTIONS), torch.randn(6)
    calls = []
    tail.register_forward_hook(lambda *args: calls.append(1))
    policy = GreedyTail(actor, 1, first_action="enumerate", tail_policy=tail, learner_steps=3)
    reference = GreedyTail(
        actor, 1, first_action="enumerate", tail_policy=_NoKeys(tail), learner_steps=3
    )
    torch.manual_seed(1)
    out = policy(td.clone())
    assert calls == []
    torch.manual_seed(1)
    expected = reference(td.clone())
    assert calls == [1]  # the reference ran the tail, whose actions were all overwritten
    assert set(out.keys(True)) == set(expected.keys(True))
    for key in expected.keys(True, True):
        assert out.get(key).dtype == expected.get(key).dtype, key
        assert torch.equal(out.get(key), expected.get(key)), key
    # A row past the learner's steps: the tail runs and acts there.
    td["step_count"][0] = 14
    assert policy(td.clone())["action"][0] == SLOWER and calls == [1, 1]
