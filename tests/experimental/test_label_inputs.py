"""label_inputs: its fits against hand-computed optima, its labelling against a plain rollout."""

import label_inputs
import pytest
import torch

from torchrl_grpo.branching.batched_search import highway_starts
from torchrl_grpo.envs import TensorHighwayEnv

pytestmark = pytest.mark.experimental


def test_the_regret_fit_weighs_a_state_by_what_a_wrong_action_costs():
    # Two states the input cannot tell apart. In the first, action 1 loses 10 to action
    # 0; in the second, action 0 loses 1 to action 1 (the other three lose 20 in both).
    # The best sets are {0} and {1}: the cross-entropy splits them about evenly, so its
    # argmax could be either. The expected regret of always 0 is (0 + 1) / 2 = 0.5, of
    # always 1 (10 + 0) / 2 = 5: the regret fit plays action 0.
    x = torch.zeros(200, 3)
    scores = torch.full((200, 5), -20.0)
    scores[:100, 0], scores[:100, 1] = 0.0, -10.0
    scores[100:, 0], scores[100:, 1] = -1.0, 0.0
    train = test = torch.arange(200)
    best_set, net = label_inputs.fit(x, scores, train, test, epochs=30)
    probs = net(x[:1]).softmax(-1)[0]
    assert abs(float(probs[0]) - 0.5) < 0.05 and abs(float(probs[1]) - 0.5) < 0.05
    regret, net = label_inputs.fit(x, scores, train, test, epochs=30, loss="regret")
    assert float(net(x[:1]).softmax(-1)[0, 0]) > 0.9
    # Half the states are won, and the other half lose 1: a mean regret of 0.5.
    assert regret["held-out accuracy"] == 0.5 and regret["held-out regret"] == 0.5
    assert regret["held-out regret > 1"] == 0.0


def test_the_danger_weight_moves_the_fit_off_an_action_that_crashes_somewhere():
    # Two states the input cannot tell apart. In 150 rows action 1 is best (1.0 against
    # 0.9 for action 0); in 50 rows action 0 is best and action 1's branch crashes (-10),
    # the only danger. The cross-entropy alone gives action 1 about 0.75. With the
    # expected crash weighted 10, the loss -(0.75 log p1 + 0.25 log p0) + 10 * 0.25 * p1
    # is least at p1 of about 0.26 (by hand, with p0 = 1 - p1): the fit plays action 0.
    x = torch.zeros(200, 3)
    scores = torch.full((200, 5), -20.0)
    scores[:150, 0], scores[:150, 1] = 0.9, 1.0
    scores[150:, 0], scores[150:, 1] = 0.0, -10.0
    danger = torch.zeros(200, 5)
    danger[150:, 1] = 1.0
    rows = torch.arange(200)
    _, plain = label_inputs.fit(x, scores, rows, rows, epochs=40)
    assert abs(float(plain(x[:1]).softmax(-1)[0, 1]) - 0.75) < 0.05
    _, careful = label_inputs.fit(x, scores, rows, rows, epochs=40, danger=danger, danger_weight=10)
    assert abs(float(careful(x[:1]).softmax(-1)[0, 1]) - 0.26) < 0.05


class _Always(torch.nn.Module):
    def __init__(self, action: int) -> None:
        super().__init__()
        self.action = action

    def forward(self, td):
        return td.set("action", torch.full(td.batch_size, self.action))


def test_labelled_states_follow_the_behaviour():
    # Driven by always-SLOWER (no random action), the labelled observations are those of
    # always-SLOWER's own episodes from the same starts, stepped here apart.
    _, observation, state, scores, crashed = label_inputs.labelled_states(
        "highway-fast-v0", "idle", 2, 0.0, 3, 500, keep_states=False, behaviour=_Always(4)
    )
    assert state is None and scores.shape == crashed.shape == (len(observation), 5)
    env = TensorHighwayEnv("highway-fast-v0", {}, num_envs=2, return_state=True)
    td = highway_starts(env, [500, 501])
    live, seen = torch.ones(2, dtype=torch.bool), []
    while live.any():
        seen.append(td["observation"][live])
        out, td = env.step_and_maybe_reset(td.set("action", torch.full((2,), 4)))
        live &= ~out["next", "done"].reshape(-1)
    assert torch.equal(torch.cat(seen).float(), observation.float())
