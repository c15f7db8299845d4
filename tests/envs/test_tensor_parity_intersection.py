"""The parity ladder on intersection-v0 (docs/sim.md): the tensor simulator against highway-env.

Worlds recorded from highway-env runs of always-FASTER, random actions and always-IDLE:
vehicles on the turns, yielding to the right of way, arriving, leaving and spawning.
The default suite runs small counts; the full ladder is ``python
benchmarks/bench_parity.py --scenario intersection-v0`` (and the ``slow`` tests here).
"""

from __future__ import annotations

import json
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

SCENARIO = "intersection-v0"
REFERENCE = Path(__file__).resolve().parents[1] / "data" / "highway_reference"
# Fresh intersection worlds replay highway-env's generator: seeds disjoint from the reference's.
FRESH_SEED = 1_000_000


@pytest.fixture(scope="module")
def intersection_worlds():
    env = TensorHighwayEnv(SCENARIO, num_envs=40, dtype=torch.float64)
    states, kinds = record_worlds(SCENARIO, recording_policies(env.config, SCENARIO), 40, seed=0)
    return env, states, kinds


def test_the_recorded_worlds_hold_turns_yields_and_hand_overs(intersection_worlds):
    _, _, kinds = intersection_worlds
    for kind in ("curved", "hand_over", "yielding", "near_miss"):
        assert kinds[kind] > 0, kinds


def test_a_same_world(intersection_worlds):
    env, states, _ = intersection_worlds
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["reward"] <= 1e-9 and worst["flags"] == 0


def test_b_one_step_every_action(intersection_worlds):
    env, states, _ = intersection_worlds
    report = one_step(env, states)
    assert report.pairs == 120
    assert report.agreement >= 0.995, report.misses


def test_c_whole_episodes(intersection_worlds):
    env, states, _ = intersection_worlds
    small = TensorHighwayEnv(SCENARIO, num_envs=8, dtype=torch.float64)
    drive = ladder_policies(SCENARIO, env.config)["drive"]
    horizons = whole_episodes(small, states[::5][:8], drive)
    assert bool((horizons == -1).all()), horizons


def test_d_fresh_worlds_match_highway_env_initial_statistics():
    from torchrl_grpo.envs.highway.parity_resets import _initial_statistics
    from torchrl_grpo.envs.highway.parity_stats import chi2_counts, ks_2samp

    reference = json.loads((REFERENCE / f"{SCENARIO}.json").read_text())
    env = TensorHighwayEnv(SCENARIO, num_envs=200, seed=FRESH_SEED, dtype=torch.float64)
    mine = _initial_statistics(env.reset()["state"], env.params)
    theirs = {k: torch.tensor([v for w in reference["initial"] for v in w[k]]) for k in mine}
    tests = [ks_2samp(mine[k], theirs[k]) for k in ("gaps", "speeds")]
    tests.append(chi2_counts(mine["lanes"], theirs["lanes"], env.params.road.lanes_count))
    assert all(p >= 0.01 / 3 for _, p in tests), tests


@pytest.mark.slow
def test_d_fresh_resets_match_highway_env_statistics():
    reference = json.loads((REFERENCE / f"{SCENARIO}.json").read_text())
    env = TensorHighwayEnv(SCENARIO, num_envs=1)
    policies = reference_policies(env.config, SCENARIO)
    table = fresh_resets(SCENARIO, reference, policies, episodes=300, seed=FRESH_SEED)
    threshold = 0.01 / len(table)  # Bonferroni over every comparison
    assert all(row["p"] >= threshold for row in table), table


@pytest.mark.slow
def test_b_on_100_worlds():
    env = TensorHighwayEnv(SCENARIO, num_envs=100, dtype=torch.float64)
    states, _ = record_worlds(SCENARIO, recording_policies(env.config, SCENARIO), 100, seed=7)
    assert same_world(env, states)["flags"] == 0
    assert one_step(env, states).agreement >= 0.995
