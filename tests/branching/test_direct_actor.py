"""The direct path of a categorical actor in branch workers: exact, or not taken."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import OneHot
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching import reset_roots
from torchrl_grpo.branching.branch_runner import BranchRunner, RolloutSetup
from torchrl_grpo.branching.direct_actor import ProbedPolicy, direct_actor
from torchrl_grpo.branching.pipe_arrays import STATE_AT_END, to_arrays
from torchrl_grpo.branching.policy_transport import PolicyCopy, pack_policy
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import KinematicsMLP, RandomPolicy, make_discrete_actor

SCENARIO = "merge-v0"


def _actor(seed: int = 0):
    torch.manual_seed(seed)
    return make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)


def _obs(n: int = 1) -> TensorDict:
    return TensorDict(observation=torch.randn(n, 5, 5), batch_size=[n])


class _Drifting(nn.Module):
    """Logits that change with every call: a copy of the input does not see the same net."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        return observation.flatten(1)[:, :5] + self.calls


def test_a_plain_categorical_actor_is_recognised_and_others_are_not():
    assert direct_actor(_actor()) is not None
    assert direct_actor(RandomPolicy(seed=0)) is None
    one_hot = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), OneHot(5))
    assert direct_actor(one_hot) is None
    net = TensorDictModule(KinematicsMLP(5, 5, out_features=5), ["observation"], ["logits"])
    assert direct_actor(TensorDictSequential(net)) is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_direct_path_writes_the_actors_entries_and_draws_bitwise(seed):
    actor = _actor(seed)
    probed = ProbedPolicy(actor)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        for step in range(6):
            td = _obs(1)
            torch.manual_seed(100 * seed + step)
            expected = actor(td.clone())
            after = torch.default_generator.get_state()
            torch.manual_seed(100 * seed + step)
            got = probed(td.clone())
            assert torch.equal(torch.default_generator.get_state(), after)
            assert sorted(got.keys(True, True)) == sorted(expected.keys(True, True))
            for key in expected.keys(True, True):
                assert torch.equal(got.get(key), expected.get(key)), key
    assert probed.probed and probed.direct is not None


def test_a_mismatch_or_another_exploration_type_runs_the_actor_itself():
    drifting = make_discrete_actor(_Drifting(), 5)
    probed = ProbedPolicy(drifting)
    assert probed.direct is not None  # the structure is plain ...
    td = _obs(1)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        first = probed(td.clone())
    assert probed.direct is None  # ... but the probe saw other logits: the actor runs
    # The probed call was the actor's own first call (the logits of call 1).
    torch.testing.assert_close(first["logits"], td["observation"].flatten(1)[:, :5] + 1)
    actor = _actor()
    probed = ProbedPolicy(actor)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = _obs(1)
        got = probed(td.clone())
        assert torch.equal(got["action"], actor(td.clone())["action"])
    assert not probed.probed  # never probed: a deterministic call is the actor's own


def test_branches_with_the_direct_path_are_bitwise_the_actors():
    env = HighwayEnv(SCENARIO, return_state=True)
    roots = reset_roots(HighwayEnv(SCENARIO, seed=0), 3, seed=1)
    keys = ["observation", *env.done_keys]
    answers = []
    for direct in (True, False):
        runner = BranchRunner(env)
        packed = pack_policy(_actor())
        setup = RolloutSetup(
            packed, keys, [*keys, *env.reward_keys], STATE_AT_END, 6, ExplorationType.RANDOM
        )
        assert runner(("setup", setup)) == ("ready",)
        runner.policy = PolicyCopy(packed, direct=direct)
        answers.append(
            [runner(("branch", b, to_arrays(roots["state"][b]), (0, b, 0)))[1] for b in range(3)]
        )
        if direct:  # the probe kept the direct path: it is what ran
            assert isinstance(runner.policy.call, ProbedPolicy)
            assert runner.policy.call.direct is not None
    for with_direct, without in zip(*answers, strict=True):
        assert with_direct["length"] == without["length"]
        for part in ("root", "next", "final"):
            a, b = with_direct[part], without[part]
            assert a.keys() == b.keys()
            for key in a:
                np.testing.assert_array_equal(a[key], b[key])
