"""The parity ladder (docs/sim.md): the tensor simulator against highway-env itself.

Rungs a-c on worlds recorded from highway-env runs (rule, random and always-FASTER
policies), imported through the bridge; rung d on fresh worlds against highway-env's
statistics recorded by scripts/highway_reference.py. benchmarks/bench_parity.py runs
the same ladder at full size.
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

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "highway_reference"


@pytest.fixture(scope="module")
def fast_worlds():
    env = TensorHighwayEnv("highway-fast-v0", num_envs=100, dtype=torch.float64)
    states, kinds = record_worlds("highway-fast-v0", recording_policies(env.config), 100, seed=0)
    return env, states, kinds


def test_the_recorded_worlds_hold_the_hard_cases(fast_worlds):
    _, _, kinds = fast_worlds
    assert kinds["changing"] > 0 and kinds["near_miss"] > 0 and kinds["crashed"] > 0


def test_a_same_world(fast_worlds):
    env, states, _ = fast_worlds
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["reward"] <= 1e-9 and worst["flags"] == 0


def test_b_one_step_every_action(fast_worlds):
    env, states, _ = fast_worlds
    report = one_step(env, states)
    assert report.pairs == 500
    assert report.agreement >= 0.995, report.misses


@pytest.mark.slow
def test_c_whole_episodes(fast_worlds):
    env, states, _ = fast_worlds
    small = TensorHighwayEnv("highway-fast-v0", num_envs=30, dtype=torch.float64)
    horizons = whole_episodes(small, states[::3][:30], recording_policies(env.config)[0])
    assert float((horizons == -1).double().mean()) >= 0.95, horizons


def test_d_fresh_resets_match_highway_env_statistics():
    reference = json.loads((REFERENCE / "highway-fast-v0.json").read_text())
    env = TensorHighwayEnv("highway-fast-v0", num_envs=1)
    table = fresh_resets("highway-fast-v0", reference, reference_policies(env.config), episodes=300)
    threshold = 0.01 / len(table)  # Bonferroni over every comparison
    assert all(row["p"] >= threshold for row in table), table


@pytest.mark.slow
def test_ladder_on_highway_v0():
    env = TensorHighwayEnv("highway-v0", num_envs=40, dtype=torch.float64)
    states, _ = record_worlds("highway-v0", recording_policies(env.config), 40, seed=0)
    worst = same_world(env, states)
    assert worst["observation"] <= 1e-9 and worst["flags"] == 0
    assert one_step(env, states).agreement >= 0.995
    path = REFERENCE / "highway-v0.json"
    if not path.is_file():
        pytest.skip(
            f"rungs a and b passed; rung d needs {path}: python scripts/highway_reference.py "
            "--scenario highway-v0 --episodes 200 --workers 2"
        )
    reference = json.loads(path.read_text())
    table = fresh_resets(
        "highway-v0", reference, reference_policies(env.config), episodes=reference["episodes"]
    )
    assert all(row["p"] >= 0.01 / len(table) for row in table), table
