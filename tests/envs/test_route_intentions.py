"""``cos_d, sin_d`` and ``observe_intentions``: where routes end, as highway-env shows it.

highway-env's Kinematics features ``cos_d, sin_d`` are ``Vehicle.destination_direction``:
the unit vector from a vehicle to the end of its route's last leg, zero without a route.
The ego's row always shows it; the other rows only with ``observe_intentions``. The
tensor simulator's tables are compared with highway-env's own (float64, before its cast)
on recorded worlds of the lane-graph scenarios and after one step from them (but on
intersection-v0, whose step spawns vehicles from the simulator's own draws); on the
highway, which has no routes, the columns are zeros.
"""

from __future__ import annotations

import pytest
import torch
from parity_helpers import recording_policies
from tensordict import TensorDict

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.envs.highway.parity import _float64_observation, record_worlds, same_world
from torchrl_grpo.envs.highway.tensor_params import check_tensor_config

DEFAULT_FEATURES = ["presence", "x", "y", "vx", "vy"]
WORLDS = 24


def _config(scenario: str, observe_intentions: bool) -> dict:
    base = check_tensor_config(scenario)["observation"]
    features = list(base.get("features") or DEFAULT_FEATURES) + ["cos_d", "sin_d"]
    return {"observation": {**base, "features": features, "observe_intentions": observe_intentions}}


@pytest.fixture(scope="module")
def worlds(request):
    """(scenario, float64 env, recorded states) with the others' intentions shown."""
    scenario = request.param
    config = _config(scenario, observe_intentions=True)
    env = TensorHighwayEnv(scenario, config, num_envs=WORLDS, dtype=torch.float64)
    recorders = recording_policies(env.config, scenario)
    states, _ = record_worlds(scenario, recorders, WORLDS, config=config, seed=5)
    return scenario, env, states


@pytest.mark.parametrize("worlds", ["roundabout-v0", "intersection-v0", "merge-v0"], indirect=True)
def test_recorded_tables_match_highway_env(worlds):
    scenario, env, states = worlds
    assert same_world(env, states)["observation"] <= 1e-9
    shown = env.reset(
        TensorDict(state=env.state_from_highway(states), batch_size=env.batch_size),
        set_state=True,
    )["observation"][..., -2:]
    if scenario == "merge-v0":  # no routes: highway-env's directions are zero
        assert bool((shown == 0).all())
    else:  # routed: the other rows show where their vehicles go, so the check has teeth
        assert float(shown[:, 1:].abs().amax()) > 0.5
        assert float(shown[:, 0].abs().amax()) > 0.5


# Not intersection-v0: its step spawns vehicles from the simulator's own draws.
@pytest.mark.parametrize("worlds", ["roundabout-v0", "merge-v0"], indirect=True)
def test_tables_after_a_step_match_highway_env(worlds):
    """The tensor step moves each route's head as highway-env pops legs; used up, zeros."""
    _, env, states = worlds
    env.reset(
        TensorDict(state=env.state_from_highway(states), batch_size=env.batch_size),
        set_state=True,
    )
    action = torch.ones(WORLDS, dtype=torch.int64)  # IDLE
    mine = env.step(TensorDict(action=action, batch_size=env.batch_size))["next", "observation"]
    hw = env.bridge.env
    for i in range(WORLDS):
        hw.set_state(states[i])
        hw.step(TensorDict(action=torch.tensor(1)))
        theirs = torch.from_numpy(_float64_observation(hw.gym_env.unwrapped))
        assert float((mine[i] - theirs).abs().max()) <= 1e-6, i


@pytest.mark.parametrize("scenario", ["roundabout-v0", "highway-fast-v0"])
def test_without_observe_intentions_only_the_ego_shows_its_own(scenario):
    config = _config(scenario, observe_intentions=False)
    env = TensorHighwayEnv(scenario, config, num_envs=8, seed=0)
    table = env.reset()["observation"][..., -2:]
    assert bool((table[:, 1:] == 0).all())
    if scenario == "roundabout-v0":  # the ego's route to its exit
        assert bool((table[:, 0].norm(dim=-1) - 1).abs().lt(1e-5).all())
    else:  # no route on the highway
        assert bool((table == 0).all())
