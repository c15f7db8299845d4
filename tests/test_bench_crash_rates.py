"""benchmarks/bench_crash_rates.py: each crash's last decisions, and the anatomy over them."""

import doctest
import re
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_crash_rates as bench  # noqa: E402

from torchrl_grpo.branching import LookaheadPolicy  # noqa: E402
from torchrl_grpo.envs import TensorHighwayEnv  # noqa: E402
from torchrl_grpo.modules import ConstantActionPolicy  # noqa: E402
from torchrl_grpo.training.transfer import tensor_episodes  # noqa: E402


def test_the_docstring_examples_run():
    assert doctest.testmod(bench).failed == 0


def test_each_crash_is_its_episode_s_last_decisions_and_only_its_own():
    # Three episodes of four steps: a crash at step 3, one at step 0, none; the rows of
    # data[steps] run 0..3 | 4 | 5 6 7 8.
    steps = torch.tensor([[1, 1, 1, 1], [1, 0, 0, 0], [1, 1, 1, 1]], dtype=torch.bool)
    # A crash flag after an episode's end is not the episode's.
    crashed = torch.tensor([[0, 0, 0, 1], [1, 0, 0, 1], [0, 0, 0, 0]], dtype=torch.bool)
    assert bench.last_decisions(steps, crashed, look_back=3) == [[1, 2, 3], [4]]
    assert bench.last_decisions(steps, crashed, look_back=10) == [[0, 1, 2, 3], [4]]


def test_the_anatomy_scores_the_last_decisions_of_each_crashed_episode(capsys):
    cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}, "max_episode_steps": 20})
    policy = ConstantActionPolicy("LANE_LEFT")
    # The crashes and their episodes' lengths, read step by step from the same rollout.
    data, steps = tensor_episodes(cfg, policy, episodes=8, seed=0, return_state=True)
    crashed = data.get(("next", "crashed")).reshape(steps.shape)
    expected = {}
    for episode in range(8):
        for t in range(int(steps[episode].sum())):
            if crashed[episode, t]:
                expected[episode] = min(3, t + 1)
                break
    assert 0 < len(expected) < 8  # always LANE_LEFT: some episodes crash, not all
    planner = LookaheadPolicy(
        TensorHighwayEnv("highway-fast-v0", num_envs=5 * 3 * len(expected)),
        ConstantActionPolicy("SLOWER"),
        2,
    )
    bench.anatomy(cfg, policy, planner, episodes=8, seed=0, last=3, sequences=True)
    out = capsys.readouterr().out
    lines = re.findall(r"  episode (\d+) \(set-point \d+ m/s\): (.*)", out)
    assert [int(episode) for episode, _ in lines] == sorted(expected)
    for episode, words in lines:  # the action taken at each decision, a costly one annotated
        assert len(re.findall(r"(?<!: )LANE_LEFT", words)) == expected[int(episode)]
    assert f"{len(expected)} crashes in 8 episodes" in out
    assert f"costly choices of {sum(expected.values())}:" in out
