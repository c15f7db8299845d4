"""bench_crash_causes: its branches crash as highway-env's do, and a crash is traced to its step."""

import bench_crash_causes as bench
import pytest
import torch
from omegaconf import OmegaConf

from torchrl_grpo.branching.batched_search import highway_starts
from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY
from torchrl_grpo.modules import ConstantActionPolicy

pytestmark = pytest.mark.experimental

CFG = OmegaConf.create({"scenario": "roundabout-v0", "config": {}, "max_episode_steps": 11})
FASTER = 3


def test_each_branch_crashes_as_highway_env_does_from_the_same_state():
    env = TensorHighwayEnv("roundabout-v0", num_envs=6, return_state=True, dtype=torch.float64)
    td = highway_starts(env, range(40000, 40006))
    for _ in range(3):  # into the roundabout, where the actions part
        td = env.step(td.set("action", torch.full((6,), FASTER))).get("next")
    states = td.get(STATE_KEY).unsqueeze(1).expand(6, 5).reshape(-1)
    actions = torch.arange(5).repeat(6)
    crashed = bench.branch_crashes(CFG, states, actions)
    highway = HighwayEnv("roundabout-v0")
    expected = []
    for state, action in zip(env.state_to_highway(states), actions.tolist(), strict=True):
        highway.set_state(state)
        hit = False
        for _ in range(11):
            out = highway.step(highway.full_action_spec.zero().set("action", torch.tensor(action)))
            hit |= bool(out["next", "crashed"])
            if out["next", "done"]:
                break
            action = bench.SLOWER
        expected.append(hit)
    assert crashed.tolist() == expected
    assert 0 < sum(expected) < len(expected)  # both outcomes occur among these branches


@pytest.mark.slow  # 24 s, a lab script's whole run: the default suite's 10-minute budget
def test_a_crash_is_replayed_from_its_saved_state_and_traced_to_its_step():
    records = bench.causes(
        CFG, ConstantActionPolicy("FASTER"), lambda obs: torch.zeros(obs.shape[0], 5), 12, 40000, 4
    )
    assert records  # always-FASTER crashes in about half of the roundabout's episodes
    for r in records:
        c, outcome = r["crash_step"], r["outcome"]
        assert r["actions"] == [FASTER] * (c + 1)
        # The branch of the action taken at the crash step is the episode's own last step.
        assert outcome[c][FASTER]
        k = r["decisive_step"]
        if k is None:  # then, the step being deterministic, always-SLOWER crashes from the start
            assert not any(o[FASTER] and not o[bench.SLOWER] for o in outcome)
            assert r["slower_from_start_crashes"]
        else:
            assert outcome[k][FASTER] and not outcome[k][bench.SLOWER]
            assert all(0.0 <= share <= 1.0 for share in r["redrawn_shares"])
        assert r["risk_taken"] == [0.0] * (c + 1)


def test_a_vehicle_is_seen_when_taking_it_out_changes_the_observation():
    env = TensorHighwayEnv("roundabout-v0", num_envs=1, return_state=True, dtype=torch.float64)
    td = highway_starts(env, [40000])
    state = td.get(STATE_KEY)[0]
    shown = int((td.get("observation")[0, 1:, 0] > 0.5).sum())  # rows beside the ego's
    seen = bench.partners_seen(CFG, state, [1, 2, 3, 4])
    assert sum(seen) == shown
    far = state.clone()
    far.get("vehicles").get("x")[2] = 5000.0  # beyond the perception distance
    assert bench.partners_seen(CFG, far, [2]) == [False]
