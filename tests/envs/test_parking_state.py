"""parking-v0 states that restored and then failed mid-step are refused (issue #20).

parking-v0's road objects include a Landmark (the ego's goal) and Obstacles (the
walls); its observation and its reward read the ego's ``goal``. A controlled,
acted-on or observing vehicle that points at an object slot, and an ego without a
goal, passed validation and raised ``AttributeError`` at the first step. Each is
refused now, naming the entry; what highway-env can step is still admitted.
"""

from __future__ import annotations

import pytest
import torch
from highway_env.vehicle.kinematics import Vehicle
from highway_env.vehicle.objects import Landmark, Obstacle
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv, StateCorruptedError
from torchrl_grpo.envs.highway.layout import CLASS_ID


@pytest.fixture(scope="module")
def parking():
    # two parked vehicles: road.vehicles holds vehicles that have no goal
    env = HighwayEnv("parking-v0", config={"vehicles_count": 2}, seed=0)
    env.reset()
    return env, env.get_state()


def _slots_of(env: HighwayEnv, state, cls: type) -> list[int]:
    class_ids = state["sim", "entities", "i16"][:, CLASS_ID].tolist()
    kinds = state["sim", "entities", "i16"][:, 0].tolist()
    wanted = env.codec.classes.index(cls)
    return [
        s for s, (k, c) in enumerate(zip(kinds, class_ids, strict=True)) if k >= 0 and c == wanted
    ]


def _steps(env: HighwayEnv, n: int = 3) -> None:
    for _ in range(n):
        out = env.step(TensorDict(action=env.action_spec.zero()))
        assert torch.isfinite(out["next", "observation"]).all()


def _goal_flags(env: HighwayEnv, state) -> tuple[torch.Tensor, int, int]:
    layout = env.codec.layout
    j = layout.names.index("goal")
    flags = state["sim", "entities", "flags"]
    return flags, layout.present.start + j, layout.is_none.start + j


@pytest.mark.parametrize("entry", ["controlled", "action_vehicle", "observer_vehicle"])
@pytest.mark.parametrize("target", [Obstacle, Landmark])
def test_a_vehicle_reference_to_an_object_slot_is_refused(parking, entry, target):
    env, clean = parking
    state = clean.clone()
    slot = _slots_of(env, state, target)[0]
    state["sim", "env", entry].fill_(slot)
    with pytest.raises(StateCorruptedError, match=rf"env\.{entry} refers to slot {slot}, a "):
        env.validate_state(state)
    with pytest.raises(StateCorruptedError, match=target.__name__):
        env.set_state(state)
    env.set_state(clean)  # the env was left as it was: a good state restores and steps
    _steps(env)


@pytest.mark.parametrize("entry", ["controlled", "action_vehicle"])
def test_a_vehicle_reference_to_another_vehicle_is_admitted(parking, entry):
    # highway-env steps it (the parked vehicle takes the actions), so it is not refused
    env, clean = parking
    state = clean.clone()
    ego = int(clean["sim", "env", "controlled"][0])
    parked = [s for s in _slots_of(env, state, Vehicle) if s != ego][0]
    state["sim", "env", entry].fill_(parked)
    # the parked vehicle is observed now (the observer defaults to it): give it a goal
    flags, present, is_none = _goal_flags(env, state)
    goal = env.codec.layout.columns["goal"].start
    flags[parked, present], flags[parked, is_none] = True, False
    state["sim", "entities", "i16"][parked, goal] = _slots_of(env, state, Landmark)[0]
    env.set_state(state)
    _steps(env)


@pytest.mark.parametrize("corruption", ["absent", "none"])
def test_an_ego_without_a_goal_is_refused(parking, corruption):
    env, clean = parking
    state = clean.clone()
    ego = int(clean["sim", "env", "controlled"][0])
    flags, present, is_none = _goal_flags(env, state)
    if corruption == "absent":
        flags[ego, present] = False
    else:
        flags[ego, is_none] = True
    word = {"absent": "absent", "none": "None"}[corruption]
    with pytest.raises(StateCorruptedError, match=rf"entities\.goal of slot {ego} is {word}"):
        env.set_state(state)
    env.set_state(clean)
    _steps(env)


def test_an_observer_without_a_goal_is_refused(parking):
    # the parked vehicles have no goal: a goal observation of one cannot be computed
    env, clean = parking
    state = clean.clone()
    ego = int(clean["sim", "env", "controlled"][0])
    parked = [s for s in _slots_of(env, state, Vehicle) if s != ego][0]
    state["sim", "env", "observer_vehicle"].fill_(parked)
    with pytest.raises(StateCorruptedError, match=rf"entities\.goal of slot {parked} is absent"):
        env.set_state(state)


@pytest.mark.parametrize("target", [Obstacle, Vehicle])
def test_any_road_object_serves_as_a_goal(parking, target):
    # highway-env observes any road object as a goal: such states step, so they restore
    env, clean = parking
    state = clean.clone()
    ego = int(clean["sim", "env", "controlled"][0])
    goal = env.codec.layout.columns["goal"].start
    state["sim", "entities", "i16"][ego, goal] = _slots_of(env, state, target)[0]
    env.set_state(state)
    _steps(env)


def test_vehicles_without_a_goal_are_admitted_where_nothing_observes_it(parking):
    env, clean = parking
    ego = int(clean["sim", "env", "controlled"][0])
    others = [s for s in _slots_of(env, clean, Vehicle) if s != ego]
    flags, present, _ = _goal_flags(env, clean)
    assert others and not flags[others, present].any()  # reached by highway-env itself
    env.set_state(clean)
    _steps(env)


def test_a_goal_in_a_slot_emptied_by_its_kind_names_the_kind(parking):
    # the fuzz harness wants the corrupted entry named: here the kind column
    env, clean = parking
    state = clean.clone()
    ego = int(clean["sim", "env", "controlled"][0])
    landmark = _slots_of(env, state, Landmark)[0]
    state["sim", "entities", "i16"][landmark, 0] = -1
    message = rf"entities\.goal of slot {ego} refers to slot {landmark}, which is empty \(kind -1\)"
    with pytest.raises(StateCorruptedError, match=message):
        env.set_state(state)
