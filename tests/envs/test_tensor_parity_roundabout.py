"""The parity ladder on roundabout-v0 (docs/sim.md): the tensor simulator against highway-env.

Worlds recorded from highway-env runs of the rule, random and always-FASTER policies:
vehicles on the ring, on the entry and exit sines, handing over between roads with
their routes. The default suite runs small counts; the full ladder is ``python
benchmarks/bench_parity.py --scenario roundabout-v0`` (and the ``slow`` tests here).
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
from torchrl_grpo.modules import (
    KinematicsLayout,
    make_scripted_policy,
)

SCENARIO = "roundabout-v0"
REFERENCE = Path(__file__).resolve().parents[1] / "data" / "highway_reference"
# Fresh roundabout worlds replay highway-env's generator: seeds disjoint from the reference's.
FRESH_SEED = 1_000_000


def rule(config):
    return make_scripted_policy("rule", KinematicsLayout.from_highway_config(config))


@pytest.fixture(scope="module")
def roundabout_worlds():
    env = TensorHighwayEnv(SCENARIO, num_envs=15, dtype=torch.float64)
    recorders = recording_policies(env.config)
    states, kinds = record_worlds(SCENARIO, recorders, 15, seed=0)
    return env, states, kinds


def test_the_recorded_worlds_hold_the_ring_and_the_hand_overs(roundabout_worlds):
    _, _, kinds = roundabout_worlds
    for kind in ("changing", "curved", "hand_over"):
        assert kinds[kind] > 0, kinds


def test_a_same_world(roundabout_worlds):
    env, states, _ = roundabout_worlds
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["reward"] <= 1e-9 and worst["flags"] == 0


def test_b_one_step_every_action(roundabout_worlds):
    env, states, _ = roundabout_worlds
    report = one_step(env, states)
    assert report.pairs == 75
    assert report.agreement >= 0.995, report.misses


@pytest.mark.slow
def test_c_whole_episodes(roundabout_worlds):
    env, states, _ = roundabout_worlds
    small = TensorHighwayEnv(SCENARIO, num_envs=5, dtype=torch.float64)
    horizons = whole_episodes(small, states[::3][:5], rule(env.config))
    assert bool((horizons == -1).all()), horizons


def test_d_fresh_worlds_match_highway_env_initial_statistics():
    from torchrl_grpo.envs.highway.parity_resets import _initial_statistics
    from torchrl_grpo.envs.highway.parity_stats import chi2_counts, ks_2samp

    reference = json.loads((REFERENCE / f"{SCENARIO}.json").read_text())
    env = TensorHighwayEnv(SCENARIO, num_envs=300, seed=FRESH_SEED, dtype=torch.float64)
    mine = _initial_statistics(env.reset()["state"], env.params)
    theirs = {k: torch.tensor([v for w in reference["initial"] for v in w[k]]) for k in mine}
    tests = [ks_2samp(mine[k], theirs[k]) for k in ("gaps", "speeds")]
    tests.append(chi2_counts(mine["lanes"], theirs["lanes"], 2))
    assert all(p >= 0.01 / 3 for _, p in tests), tests


@pytest.mark.slow
def test_d_fresh_resets_match_highway_env_statistics():
    reference = json.loads((REFERENCE / f"{SCENARIO}.json").read_text())
    env = TensorHighwayEnv(SCENARIO, num_envs=1)
    policies = reference_policies(env.config)
    table = fresh_resets(SCENARIO, reference, policies, episodes=200, seed=FRESH_SEED)
    threshold = 0.01 / len(table)  # Bonferroni over every comparison
    assert all(row["p"] >= threshold for row in table), table


@pytest.mark.slow
def test_b_on_100_worlds():
    env = TensorHighwayEnv(SCENARIO, num_envs=100, dtype=torch.float64)
    recorders = recording_policies(env.config)
    states, _ = record_worlds(SCENARIO, recorders, 100, seed=7)
    assert same_world(env, states)["flags"] == 0
    assert one_step(env, states).agreement >= 0.995
