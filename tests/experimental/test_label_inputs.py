"""label_inputs' fits: the best-set cross-entropy and the expected regret, by hand."""

import label_inputs
import pytest
import torch

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
