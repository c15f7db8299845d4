"""HorizonBootstrap against hand-computed tails, on the layouts the collectors write."""

from __future__ import annotations

import ast
import inspect

import pytest
import torch
from tensordict import TensorDict

import torchrl_grpo.objectives.bootstrap as bootstrap_module
from torchrl_grpo.objectives import HorizonBootstrap

# One group of three 4-step branches from a root at episode step 20 of a 30-step
# episode (all stored as [R, G, T] = [1, 3, 4]):
# - branch 0 survives the horizon: 4 valid steps, ends at step 24, 6 steps left;
# - branch 1 crashes at its 2nd step (terminated): no tail;
# - branch 2 ends after 3 steps without being terminated (the env truncated it): a tail
#   for the 30 - 23 = 7 steps left.
REWARD = [[1.0, 0.5, 1.0, 0.5], [1.0, 0.0, 9.0, 9.0], [0.5, 0.5, 0.5, 9.0]]
MASK = [[True] * 4, [True, True, False, False], [True, True, True, False]]
TERMINATED = [[False] * 4, [False, True, False, False], [False] * 4]
# The mean reward over the 9 valid steps: (3 + 1 + 1.5) / 9.
RATE = 5.5 / 9
TAILS = [RATE * 6, 0.0, RATE * 7]
LAST = [3, 1, 2]


def _batch(root_step: int = 20, trailing_one: bool = True) -> TensorDict:
    reward = torch.tensor([REWARD])
    terminated = torch.tensor([TERMINATED])
    if trailing_one:
        reward, terminated = reward.unsqueeze(-1), terminated.unsqueeze(-1)
    return TensorDict(
        {
            "mask": torch.tensor([MASK]),
            "root_step": torch.full((1, 3, 4), root_step),
            ("next", "reward"): reward,
            ("next", "terminated"): terminated,
        },
        batch_size=[1, 3, 4],
    )


def _expected(tails: list[float]) -> tuple[torch.Tensor, torch.Tensor]:
    bonus = torch.zeros(1, 3, 4)
    for branch, (tail, last) in enumerate(zip(tails, LAST, strict=True)):
        bonus[0, branch, last] = tail
    return torch.tensor([REWARD]) + bonus, bonus


@pytest.mark.parametrize("trailing_one", [True, False], ids=["[R,G,T,1]", "[R,G,T]"])
def test_tails_of_truncated_branches_match_hand_computation(trailing_one):
    out = HorizonBootstrap(step_limit=30)(_batch(trailing_one=trailing_one))
    train, bonus = _expected(TAILS)
    shape = (1, 3, 4, 1) if trailing_one else (1, 3, 4)
    assert out["next", "train_reward"].shape == shape
    torch.testing.assert_close(out["next", "train_reward"].reshape(1, 3, 4), train)
    torch.testing.assert_close(out["bootstrap"].reshape(1, 3, 4), bonus)
    # The env's reward is untouched.
    assert torch.equal(out["next", "reward"].reshape(1, 3, 4), torch.tensor([REWARD]))


def test_no_tail_past_the_episode_end_and_none_mode_copies_the_reward():
    # A root at step 28: every branch ends at step 30 or later, no step is left.
    out = HorizonBootstrap(step_limit=30)(_batch(root_step=28))
    train, bonus = _expected([0.0, 0.0, 0.0])
    torch.testing.assert_close(out["next", "train_reward"].squeeze(-1), train)
    assert not out["bootstrap"].any()
    # mode="none": the training reward is the env's, whatever the branch did.
    out = HorizonBootstrap(step_limit=30, mode="none")(_batch())
    assert torch.equal(out["next", "train_reward"], out["next", "reward"])
    assert not out["bootstrap"].any()


def test_a_flat_batch_of_branches_gives_the_same_tails():
    # [N, T]: the three branches without the group dimension.
    batch = _batch().squeeze(0)
    out = HorizonBootstrap(step_limit=30)(batch)
    train, _ = _expected(TAILS)
    torch.testing.assert_close(out["next", "train_reward"].squeeze(-1), train[0])


def test_keys_are_renamed_with_set_keys_and_unknown_names_refused():
    batch = _batch().rename_key_("mask", "valid").rename_key_("root_step", "start")
    module = HorizonBootstrap(step_limit=30).set_keys(
        mask="valid", root_step="start", train_reward="r", bootstrap="tail"
    )
    assert module.in_keys == [("next", "reward"), ("next", "terminated"), "valid", "start"]
    assert module.out_keys == ["r", "tail"]
    out = module(batch)
    torch.testing.assert_close(out["r"].squeeze(-1), _expected(TAILS)[0])
    with pytest.raises(ValueError, match="not accepted keys"):
        HorizonBootstrap(step_limit=30).set_keys(rewards="r")
    with pytest.raises(ValueError, match="mode"):
        HorizonBootstrap(step_limit=30, mode="critic")


def test_the_module_imports_nothing_from_branching():
    tree = ast.parse(inspect.getsource(bootstrap_module))
    imported = [
        node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module
    ] + [
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.Import)
        for alias in node.names
    ]
    assert imported and not [name for name in imported if "branching" in name]
