"""The parity ladder on merge-v0, roundabout-v0 and intersection-v0 (docs/sim.md).

The tensor simulator against highway-env itself, on worlds recorded from highway-env
runs (merge-v0 and roundabout-v0: the rule policy, random actions and always-FASTER;
intersection-v0: always-FASTER, random actions and always-IDLE). Each scenario's worlds
hold what is new in it: the ramp (forbidden lanes) and the sine lane of merge-v0, the
ring and its entry and exit sines of roundabout-v0, the turns and yields of
intersection-v0, and road hand-overs in all three. The default suite runs small counts;
the full ladder is ``python benchmarks/bench_parity.py --scenario <id>`` (and the
``slow`` tests here).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from parity_helpers import recording_policies, reference_policies

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.envs.highway.parity import (
    fresh_resets,
    one_step,
    record_worlds,
    same_world,
    whole_episodes,
)
from torchrl_grpo.envs.highway.parity_policies import ladder_policies

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "highway_reference"
# Fresh worlds replay highway-env's generator: seeds disjoint from the reference's.
FRESH_SEED = 1_000_000


@dataclass(frozen=True)
class Ladder:
    """One scenario's rungs: what its recorded worlds hold and how many are checked."""

    scenario: str
    worlds: int  # recorded worlds of rungs a and b
    kinds: tuple[str, ...]  # what at least one recorded world holds
    actions: int  # rung b steps every world with each of them
    episodes_every: int  # rung c replays worlds[::episodes_every][:episode_envs]
    episode_envs: int
    fresh_envs: int  # fresh worlds of rung d's initial statistics
    reset_episodes: int  # highway-env episodes of rung d's fresh resets


MERGE = Ladder(
    "merge-v0", 15, ("changing", "crashed", "curved", "forbidden", "hand_over"), 5, 3, 5, 300, 200
)
ROUNDABOUT = Ladder("roundabout-v0", 15, ("changing", "curved", "hand_over"), 5, 3, 5, 300, 200)
INTERSECTION = Ladder(
    "intersection-v0", 40, ("curved", "hand_over", "yielding", "near_miss"), 3, 5, 8, 200, 300
)
LADDERS = [pytest.param(ladder, id=ladder.scenario) for ladder in (MERGE, ROUNDABOUT, INTERSECTION)]
# Rung c in the default suite where it is quick: intersection's episodes are short.
WHOLE_EPISODES = [
    pytest.param(MERGE, id=MERGE.scenario, marks=pytest.mark.slow),
    pytest.param(ROUNDABOUT, id=ROUNDABOUT.scenario, marks=pytest.mark.slow),
    pytest.param(INTERSECTION, id=INTERSECTION.scenario),
]


@pytest.fixture(scope="module")
def recorded(request):
    """The worlds of a scenario's ladder: (ladder, a float64 env, states, kinds)."""
    ladder = request.param
    env = TensorHighwayEnv(ladder.scenario, num_envs=ladder.worlds, dtype=torch.float64)
    recorders = recording_policies(env.config, ladder.scenario)
    states, kinds = record_worlds(ladder.scenario, recorders, ladder.worlds, seed=0)
    return ladder, env, states, kinds


@pytest.mark.parametrize("recorded", LADDERS, indirect=True)
def test_the_recorded_worlds_hold_what_the_scenario_adds(recorded):
    ladder, _, _, kinds = recorded
    for kind in ladder.kinds:
        assert kinds[kind] > 0, kinds


@pytest.mark.parametrize("recorded", LADDERS, indirect=True)
def test_a_same_world(recorded):
    _, env, states, _ = recorded
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["reward"] <= 1e-9 and worst["flags"] == 0


@pytest.mark.parametrize("recorded", LADDERS, indirect=True)
def test_b_one_step_every_action(recorded):
    ladder, env, states, _ = recorded
    report = one_step(env, states)
    assert report.pairs == ladder.worlds * ladder.actions  # 75, 75 and 120
    assert report.agreement >= 0.995, report.misses


@pytest.mark.parametrize("recorded", WHOLE_EPISODES, indirect=True)
def test_c_whole_episodes(recorded):
    ladder, env, states, _ = recorded
    small = TensorHighwayEnv(ladder.scenario, num_envs=ladder.episode_envs, dtype=torch.float64)
    drive = ladder_policies(ladder.scenario, env.config)["drive"]
    worlds = states[:: ladder.episodes_every][: ladder.episode_envs]
    horizons = whole_episodes(small, worlds, drive)
    assert bool((horizons == -1).all()), horizons


@pytest.mark.parametrize("ladder", LADDERS)
def test_d_fresh_worlds_match_highway_env_initial_statistics(ladder):
    from torchrl_grpo.envs.highway.parity_resets import _initial_statistics
    from torchrl_grpo.envs.highway.parity_stats import chi2_counts, ks_2samp

    reference = json.loads((REFERENCE / f"{ladder.scenario}.json").read_text())
    env = TensorHighwayEnv(
        ladder.scenario, num_envs=ladder.fresh_envs, seed=FRESH_SEED, dtype=torch.float64
    )
    mine = _initial_statistics(env.reset()["state"], env.params)
    theirs = {k: torch.tensor([v for w in reference["initial"] for v in w[k]]) for k in mine}
    tests = [ks_2samp(mine[k], theirs[k]) for k in ("gaps", "speeds")]
    lanes = 1 + int(max(t["lanes"].max() for t in (mine, theirs)))
    tests.append(chi2_counts(mine["lanes"], theirs["lanes"], lanes))
    assert all(p >= 0.01 / 3 for _, p in tests), tests


@pytest.mark.slow
@pytest.mark.parametrize("ladder", LADDERS)
def test_d_fresh_resets_match_highway_env_statistics(ladder):
    reference = json.loads((REFERENCE / f"{ladder.scenario}.json").read_text())
    env = TensorHighwayEnv(ladder.scenario, num_envs=1)
    policies = reference_policies(env.config, ladder.scenario)
    table = fresh_resets(
        ladder.scenario, reference, policies, episodes=ladder.reset_episodes, seed=FRESH_SEED
    )
    threshold = 0.01 / len(table)  # Bonferroni over every comparison
    assert all(row["p"] >= threshold for row in table), table


@pytest.mark.slow
@pytest.mark.parametrize("ladder", LADDERS)
def test_b_on_100_worlds(ladder):
    env = TensorHighwayEnv(ladder.scenario, num_envs=100, dtype=torch.float64)
    recorders = recording_policies(env.config, ladder.scenario)
    states, _ = record_worlds(ladder.scenario, recorders, 100, seed=7)
    assert same_world(env, states)["flags"] == 0
    assert one_step(env, states).agreement >= 0.995
