"""A configured Kinematics ``features_range`` means what it means in highway-env.

highway-env normalises by a configured ``features_range`` as given (a feature it does
not name stays in metres and m/s), and fixes the ranges itself only when none is
configured. The reference is highway-env's own observation of the same recorded worlds.
"""

import pytest
import torch
from highway_env.envs.intersection_env import IntersectionEnv
from tensordict import TensorDict

from torchrl_grpo.envs import TENSOR_SCENARIOS, TensorHighwayEnv
from torchrl_grpo.envs.highway.parity import record_worlds, same_world
from torchrl_grpo.envs.highway.parity_policies import ladder_policies

# x wider than the default 200 m (merge-v0's ego passes x = 200 m before its episode
# ends), vx narrower; y and vy unnamed, so left unnormalised.
RANGES = {"x": [-400.0, 400.0], "vx": [-60.0, 60.0]}


def _config(scenario: str) -> dict:
    base = IntersectionEnv.default_config()["observation"] if scenario == "intersection-v0" else {}
    return {"observation": {**base, "type": "Kinematics", "features_range": RANGES}}


@pytest.mark.parametrize(
    "scenario",
    # highway-v0 observes as highway-fast-v0 does, over more vehicles: -m slow (time budget).
    [pytest.param(s, marks=pytest.mark.slow) if s == "highway-v0" else s for s in TENSOR_SCENARIOS],
)
def test_configured_ranges_observe_as_highway_env_does(scenario):
    config = _config(scenario)
    policies = list(ladder_policies(scenario, config).values())
    states, _ = record_worlds(scenario, policies, 24, config=config, seed=3)
    env = TensorHighwayEnv(scenario, config, num_envs=24, dtype=torch.float64)
    assert same_world(env, states) == {"observation": 0.0, "reward": 0.0, "flags": 0}
    ranges = dict(env.params.observation.features_range)
    assert ranges == {k: tuple(v) for k, v in RANGES.items()}


def test_configured_ranges_reach_the_cpp_step():
    config = _config("highway-fast-v0")
    envs = [
        TensorHighwayEnv(config=config, num_envs=8, seed=1, dtype=torch.float64, native=flag)
        for flag in (True, False)
    ]
    actions = [(torch.arange(8) + t) % 5 for t in range(4)]
    outs = []
    for env in envs:
        env.reset()
        steps = [env.step(TensorDict(action=a, batch_size=[8]))["next"] for a in actions]
        outs.append(torch.stack([step["observation"] for step in steps]))
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=1e-9)
    # At a reset, the egos' x is normalised by 400 m and their y left in metres.
    env = envs[0]
    ego, state = env.reset()["observation"][:, 0], env.get_state()["vehicles"][:, 0]
    torch.testing.assert_close(ego[:, 1] * 400, state["x"], rtol=0, atol=1e-9)
    torch.testing.assert_close(ego[:, 2], state["y"], rtol=0, atol=0)


@pytest.mark.parametrize("scenario", ["highway-fast-v0", "merge-v0"])
def test_a_range_that_is_not_low_below_high_is_a_value_error(scenario):
    config = {"observation": {"type": "Kinematics", "features_range": {"x": [5.0, 5.0]}}}
    with pytest.raises(ValueError, match="features_range"):
        TensorHighwayEnv(scenario, config, num_envs=2)
