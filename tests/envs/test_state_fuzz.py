"""No state hangs or kills anything (issue #20, item 1).

Every column of the packed tables and every other entry of states from several
scenarios is corrupted (zero, NaN, inf, sign flip, bit flips, truncation). Each case
runs in a warm worker process under a timeout: it is either refused at restore with a
``SnapshotError`` that names the entry, or it restores, steps, resets and steps again
with finite outputs. The default suite runs a sample; ``-m slow`` runs the full sweep.
"""

from __future__ import annotations

import random
from collections import Counter

import pytest
import torch
from state_fuzz import WarmWorker, cases, make_env
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv, SnapshotParallelEnv, StateCorruptedError

SAMPLE_SCENARIOS = ("merge-v0", "intersection-v0")
ALL_SCENARIOS = (
    "highway-fast-v0",
    "merge-v0",
    "intersection-v0",
    "racetrack-v0",
    "parking-v0",
    "lane-keeping-v0",
)


@pytest.fixture(scope="module")
def worker():
    w = WarmWorker(timeout=30.0)
    yield w
    w.close()


def _failures(worker: WarmWorker, todo, tally: Counter | None = None) -> list[str]:
    failures = []
    for case in todo:
        outcome, message = worker.run(case)
        if tally is not None:
            tally[outcome] += 1
        if outcome == "refused":
            # The error names the entry (a packed column by its field): truncations name
            # the missing or malformed entry itself.
            wanted = case.name.split(".")[-1]
            if wanted not in message:
                failures.append(f"{case}: refused without naming {wanted!r}: {message}")
        elif outcome != "ok":
            failures.append(f"{case}: {outcome}: {message}")
    return failures


def _sample(scenario: str, k: int, seed: int) -> list:
    every = cases(make_env(scenario), scenario)
    rng = random.Random(seed)
    # the named cases of the issue, then a random sample of every other entry
    named = [
        c
        for c in every
        if (c.key[-1] == "rng" and c.mode == "zero")
        or (c.name in ("speed", "heading", "target_speed") and c.mode in ("nan", "inf"))
        or (c.key[:2] == ("output", "observation") and c.mode == "nan")
    ]
    return named + rng.sample(every, k)


@pytest.mark.parametrize("scenario", SAMPLE_SCENARIOS)
def test_a_sample_of_corrupted_states_is_refused_or_steps(worker, scenario):
    failures = _failures(worker, _sample(scenario, 30, seed=len(scenario)))
    assert not failures, "\n".join(failures)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ALL_SCENARIOS)
def test_every_corrupted_column_is_refused_or_steps(worker, scenario):
    todo = cases(make_env(scenario), scenario)
    tally = Counter()
    failures = _failures(worker, todo, tally)
    # the figures docs/envs.md quotes (shown with -s or -rP)
    print(f"{scenario}: {len(todo)} cases, {tally['refused']} refused, {tally['ok']} stepped")
    assert not failures, "\n".join(failures[:40]) + f"\n({len(failures)} in all)"
    assert sum(tally.values()) == len(todo)


# ------------------------------------------------------------------ the cases
def _zeroed_rng(state):
    state["sim", "env", "rng"].fill_(0)


def _float(key):
    def corrupt(state, env=None):
        state["sim", *key].view(torch.float64).fill_(float("nan"))

    return corrupt


def test_a_zeroed_generator_is_refused_and_the_env_still_resets():
    env = HighwayEnv("highway-fast-v0", seed=0)
    state = env.get_state()
    _zeroed_rng(state)
    with pytest.raises(StateCorruptedError, match=r"env\.rng"):
        env.validate_state(state)
    with pytest.raises(StateCorruptedError, match=r"env\.rng"):
        env.set_state(state)
    env.reset()  # hung forever in numpy before


@pytest.mark.parametrize("field", ["speed", "heading", "target_speed"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), 1e300])
def test_a_non_finite_vehicle_float_is_refused_naming_it(field, value):
    env = HighwayEnv("merge-v0", seed=0)
    state = env.get_state()
    column = env.codec.layout.columns[field]
    f64 = state["sim", "entities", "f64"].view(torch.float64)
    f64[1, column.start] = value
    with pytest.raises(StateCorruptedError, match=rf"entities\.{field} of slot 1"):
        env.set_state(state)


def test_a_nan_observation_inside_a_state_is_refused():
    env = HighwayEnv("merge-v0", seed=0)
    state = env.get_state()
    state["output", "observation"].view(torch.float32)[0, 1] = float("nan")
    with pytest.raises(StateCorruptedError, match=r"output\.observation"):
        env.set_state(state)


def test_reachable_states_are_admitted():
    # speeds below 0, speeds beyond the vehicle's range and unwrapped headings happen
    env = HighwayEnv("merge-v0", seed=0)
    state = env.get_state()
    f64 = state["sim", "entities", "f64"].view(torch.float64)
    layout = env.codec.layout
    f64[1, layout.columns["speed"].start] = -3.0
    f64[2, layout.columns["speed"].start] = 61.0
    f64[3, layout.columns["heading"].start] = 40.0
    env.set_state(state)
    for _ in range(3):
        env.step(TensorDict(action=env.action_spec.zero()))


def test_lane_keeping_without_its_lane_is_refused():
    # its reward reads env.lane every step: a state without one (a sign-flipped lane
    # code reads as "no lane") raised AttributeError mid-step
    env = HighwayEnv("lane-keeping-v0", seed=0)
    state = env.get_state()
    state["sim", "env", "lane"].fill_(-2)
    with pytest.raises(StateCorruptedError, match=r"env\.lane is \[-2, -2, -2\], no lane"):
        env.set_state(state)
    env.reset()
    env.step(TensorDict(action=env.action_spec.zero()))


def test_parallel_envs_stay_usable_after_refused_states():
    env = HighwayEnv("merge-v0", seed=0)
    clean = env.get_state()
    broken = []
    for corrupt in (_zeroed_rng, _float(("entities", "f64"))):
        state = clean.clone()
        corrupt(state)
        broken.append(state)
    obs_nan = clean.clone()
    obs_nan["output", "observation"].view(torch.float32).fill_(float("nan"))
    broken.append(obs_nan)
    penv = SnapshotParallelEnv(2, lambda: HighwayEnv("merge-v0", seed=0))
    try:
        for state in broken:
            states = torch.stack([clean, state])
            with pytest.raises(StateCorruptedError):
                penv.reset(TensorDict(state=states, batch_size=[2]), set_state=True)
            # the workers are alive: a good batch restores and steps
            out = penv.reset(
                TensorDict(state=torch.stack([clean, clean]), batch_size=[2]), set_state=True
            )
            assert torch.isfinite(out["observation"]).all()
            step = penv.step(out.set("action", penv.action_spec.zero()))
            assert torch.isfinite(step["next", "observation"]).all()
    finally:
        penv.close()
