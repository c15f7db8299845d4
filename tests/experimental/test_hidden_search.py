"""bench_hidden_search: the redraws keep what is seen, and the search is the plain one's."""

import subprocess
import sys
from pathlib import Path

import bench_hidden_search as bench
import pytest
import torch
from tensordict import TensorDict

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.keys import MASK, STATE
from torchrl_grpo.branching.lookahead import branch_returns
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import make_scripted_policy
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.sim.roundabout_reset import route_paths
from torchrl_grpo.training import compose_config, make_env, make_policy

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.experimental

# Everything an observation is read from, and more: only delta and the routes may move.
SEEN = ("x", "y", "heading", "speed", "target_speed", "lane", "target_lane", "present")


def _worlds_after(scenario: str, n: int, seed: int, action: int, steps: int):
    """``n`` worlds of ``scenario`` after ``steps`` steps of ``action``: (env, tensordict)."""
    env = TensorHighwayEnv(scenario, num_envs=n, return_state=True, seed=seed)
    td = env.reset()
    for _ in range(steps):
        td["action"] = torch.full((n,), action)
        td = env.step_and_maybe_reset(td)[1]
    return env, td


@pytest.fixture(scope="module")
def worlds():
    """Roundabout states a few steps in: vehicles on entries, the ring and exits."""
    return _worlds_after(bench.SCENARIO, 64, seed=3, action=1, steps=4)


def test_a_redraw_moves_only_the_other_vehicles_hidden_variables(worlds):
    env, td = worlds
    state = td[STATE]
    new = bench.redraw_hidden(state, env.params, "both", torch.Generator().manual_seed(0))
    for key in SEEN:
        assert torch.equal(new["vehicles", key], state["vehicles", key]), key
    delta = new["vehicles", "delta"]
    assert torch.equal(delta[:, 0], state["vehicles", "delta"][:, 0])
    assert ((delta[:, 1:] >= 3.5) & (delta[:, 1:] <= 4.5)).all()
    assert not torch.equal(delta, state["vehicles", "delta"])
    # The ego keeps its route; a redrawn route starts at the vehicle's lane.
    legs, head = new["route", "legs"], new["route", "head"]
    assert torch.equal(legs[:, 0], state["route", "legs"][:, 0])
    moved = (legs != state["route", "legs"]).any(-1) | (head != state["route", "head"])
    assert moved.any()
    assert torch.equal(legs[..., 0][moved], new["vehicles", "lane"][moved])
    assert (head[moved] == 0).all()


def test_routes_are_redrawn_among_the_exits_and_only_where_all_are_reachable(worlds):
    env, td = worlds
    state, params = td[STATE], env.params
    paths = route_paths(params, torch.device("cpu"))
    exits = torch.tensor(params.traffic.destinations)
    road = torch.tensor(params.road.road)[state["vehicles", "lane"]]
    reachable = (paths[:, exits, 0] >= 0).all(-1)[road]
    reachable[:, 0] = False
    seen = set()
    for k in range(20):
        new = bench.redraw_hidden(state, params, "route", torch.Generator().manual_seed(k))
        legs = new["route", "legs"]
        # Off the reachable roads, nothing moves.
        assert torch.equal(legs[~reachable], state["route", "legs"][~reachable])
        # On them, the tail of each route is one exit's path from the vehicle's road.
        tails = legs[reachable][:, 1:]
        options = paths[road[reachable]][:, exits, : tails.shape[-1]]
        match = (options == tails.unsqueeze(1)).all(-1)
        assert match.any(-1).all()
        seen |= set(match.float().argmax(-1).tolist())
    assert seen == {0, 1, 2}


def _true_destinations(state, params):
    """Each vehicle's destination index (into the exits), read back from its route; -1: none."""
    paths = route_paths(params, torch.device("cpu"))
    exits = torch.tensor(params.traffic.destinations)
    legs, head = state["route", "legs"], state["route", "head"]
    length = legs.shape[-1]
    ahead = head.unsqueeze(-1) + 1 + torch.arange(length - 1)
    rest = torch.where(ahead < length, legs.gather(-1, ahead.clamp(max=length - 1)), -1)
    road = torch.tensor(params.road.road)[state["vehicles", "lane"]]
    match = (paths[road][:, :, exits] == rest.unsqueeze(-2)).all(-1)
    return torch.where(match.any(-1), match.float().argmax(-1), -1)


def test_a_route_encoded_as_the_redraw_does_drives_as_the_original(worlds):
    """The redraw's encoding of a destination ([lane] + path, from its start) is faithful:
    re-encoding each vehicle's own destination that way changes no future bit.

    A vehicle can leave its route (highway-env then picks its turns at random); those
    have no destination to re-encode and keep their routes here.
    """
    env, td = worlds
    state, params = td[STATE], env.params
    exits = torch.tensor(params.traffic.destinations)
    own = _true_destinations(state, params)
    paths = route_paths(params, torch.device("cpu"))
    lane = state["vehicles", "lane"]
    road = torch.tensor(params.road.road)[lane]
    recode = (paths[:, exits, 0] >= 0).all(-1)[road] & (own >= 0)
    recode[:, 0] = False
    # Mid-route vehicles among them: their head moves back to 0 in the new encoding.
    assert (recode & (state["route", "head"] > 0)).any()
    legs = torch.cat([lane.unsqueeze(-1), paths[road, exits[own.clamp(min=0)]]], -1)
    recoded = state.clone()
    recoded["route", "legs"] = torch.where(recode.unsqueeze(-1), legs, state["route", "legs"])
    recoded["route", "head"] = torch.where(recode, 0, state["route", "head"])
    assert not torch.equal(recoded["route", "legs"], state["route", "legs"])
    futures = []
    for start in (state, recoded):
        sim = TensorHighwayEnv(bench.SCENARIO, num_envs=len(start), return_state=True)
        out = sim.reset(TensorDict({STATE: start}, batch_size=[len(start)]), set_state=True)
        for _ in range(8):
            out["action"] = torch.full((len(start),), 1)
            out = sim.step(out)["next"]
        futures.append(out["state", "vehicles"])
    for key in ("x", "y", "speed", "heading", "crashed"):
        assert torch.equal(futures[0][key], futures[1][key]), key


@pytest.mark.parametrize("base", ["idle", "slower"])
def test_without_a_redraw_it_is_the_plain_search_and_the_penalty_counts_crashes(worlds, base):
    env, td = worlds
    n = 8
    roots = td[:n]
    plain = LookaheadPolicy(
        TensorHighwayEnv(bench.SCENARIO, num_envs=5 * n), make_scripted_policy(base), 11
    )
    data = plain.branches(roots)
    crashed = data.get(("next", "crashed")).reshape(data.get(MASK).shape) & data.get(MASK)
    expected = branch_returns(data) - 5.0 * crashed.any(-1).double()
    search = bench.RedrawnSearch(
        TensorHighwayEnv(bench.SCENARIO, num_envs=5 * n * 2), 11, copies=2, redraw="none",
        aggregate="min", crash_penalty=5.0, seed=0, base=base,
    )  # fmt: skip
    assert torch.equal(search.returns(roots), expected)
    assert crashed.any(), "no branch crashed: the penalty went untested"


def test_bad_settings_are_refused_by_name(worlds):
    env, td = worlds
    with pytest.raises(ValueError, match="redraw must be one of"):
        bench.redraw_hidden(td[STATE], env.params, "drivers", torch.Generator())
    with pytest.raises(ValueError, match="redraws are for roundabout-v0 and highway-fast-v0"):
        merge = TensorHighwayEnv("merge-v0", num_envs=1)
        bench.redraw_hidden(td[STATE], merge.params, "delta", torch.Generator())
    with pytest.raises(ValueError, match="aggregate must be"):
        bench.RedrawnSearch(
            env, 11, copies=1, redraw="none", aggregate="max", crash_penalty=0.0, seed=0
        )


@pytest.mark.slow  # about a minute: the episodes' starts come from highway-env
def test_a_two_episode_run_prints_its_table():
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "lab" / "bench_hidden_search.py"),
         "--episodes", "2", "--copies", "2", "--redraw", "none", "both"],
        capture_output=True, text=True, check=True, timeout=600,
    )  # fmt: skip
    rows = [line for line in out.stderr.splitlines() if line.startswith("| ")]
    assert rows[0].startswith("| policy | return |")
    assert rows[1].startswith("| always-SLOWER | 9.1")
    assert rows[2].startswith("| redraw none, 1 copies, mean, crash penalty 0 |")
    assert rows[3].startswith("| redraw both, 2 copies, mean, crash penalty 0 |")


@pytest.fixture(scope="module")
def highway_worlds():
    """highway-fast-v0 states a few steps in (always-FASTER), the traffic under way."""
    return _worlds_after(bench.HIGHWAY, 32, seed=5, action=3, steps=3)


@pytest.mark.parametrize(
    ("redraw", "moved"),
    [("delta", {"delta"}), ("target", {"target_speed"}), ("timer", {"timer"}),
     ("all", {"delta", "target_speed", "timer"}), ("none", set())],
)  # fmt: skip
def test_a_highway_redraw_moves_only_its_hidden_columns_of_the_others(
    highway_worlds, redraw, moved
):
    env, td = highway_worlds
    state, params = td[STATE], env.params
    new = bench.redraw_hidden(state, params, redraw, torch.Generator().manual_seed(1))
    limit = params.road.speed_limit
    bounds = {
        "delta": params.idm.delta_range,
        "target_speed": (params.traffic.speed_low * limit, params.traffic.speed_high * limit),
        "timer": (0.0, params.idm.lane_change_delay),
    }
    for key in state["vehicles"].keys():
        old, now = state["vehicles", key], new["vehicles", key]
        if key not in moved:
            assert torch.equal(old, now), key
            continue
        assert torch.equal(old[:, 0], now[:, 0]), f"the ego's {key} moved"
        assert not torch.equal(old[:, 1:], now[:, 1:]), key
        low, high = bounds[key]
        assert ((now[:, 1:] >= low) & (now[:, 1:] <= high)).all(), key
    if "target_speed" in moved:
        # Never below a car's speed: IDM drives no car faster than its target speed.
        speed = state["vehicles", "speed"][:, 1:]
        assert (new["vehicles", "target_speed"][:, 1:] >= speed).all()
    # Hand check of the bounds: U(21, 24) m/s target speeds, U(3.5, 4.5) exponents.
    assert bounds["target_speed"] == pytest.approx((21.0, 24.0))
    assert tuple(bounds["delta"]) == (3.5, 4.5)


def test_a_highway_search_over_a_network_without_a_redraw_is_the_plain_search(highway_worlds):
    env, td = highway_worlds
    cfg = compose_config(["experiment=smoke", "model=mlp"])
    policy = make_policy(cfg.model, make_env(cfg.env, seed=0))
    roots = td[:6]
    plain = LookaheadPolicy(
        TensorHighwayEnv(bench.HIGHWAY, num_envs=30), DeterministicActor(policy), 8
    )
    expected = branch_returns(plain.branches(roots))
    search = bench.RedrawnSearch(
        TensorHighwayEnv(bench.HIGHWAY, num_envs=30), 8, copies=1, redraw="none",
        aggregate="mean", crash_penalty=0.0, seed=0, base=policy,
    )  # fmt: skip
    assert torch.equal(search.returns(roots), expected)
    with pytest.raises(ValueError, match="redraw must be one of"):
        bench.redraw_hidden(td[STATE], env.params, "route", torch.Generator())


def test_target_speeds_are_drawn_at_or_above_the_speed_unless_wide(highway_worlds):
    env, td = highway_worlds
    state = td[STATE]
    speed = state["vehicles", "speed"][:, 1:]
    present = state["vehicles", "present"][:, 1:]
    for wide in (False, True):
        new = bench.redraw_hidden(
            state, env.params, "target", torch.Generator().manual_seed(2), wide_targets=wide
        )
        below = (new["vehicles", "target_speed"][:, 1:] < speed) & present
        # The whole range puts some cars' targets below their speed; the observed one never.
        assert bool(below.any()) == wide


@pytest.mark.parametrize(
    "observation", [None, {"type": "Kinematics", "vehicles_count": 10, "see_behind": True}]
)
def test_dropping_the_unseen_vehicles_keeps_the_observation_and_only_the_observed(
    highway_worlds, observation
):
    _, td = highway_worlds
    state = td[STATE]
    config = None if observation is None else {"observation": observation}
    kept = bench.without_unseen(state, bench.HIGHWAY, config)
    present = kept["vehicles", "present"]
    assert (present <= state["vehicles", "present"]).all()
    assert present.sum() < state["vehicles", "present"].sum()  # traffic the table leaves out
    # The same observation from both states, and its rows are the vehicles kept.
    seen = []
    for world in (state, kept):
        env = TensorHighwayEnv(bench.HIGHWAY, config, num_envs=32, return_state=True)
        world = world.clone().set("fingerprint", torch.full((32,), env.fingerprint))
        seen.append(env.reset(TensorDict({STATE: world}, [32]), set_state=True)["observation"])
    assert torch.equal(seen[0], seen[1])
    assert torch.equal(present.sum(1), (seen[0][:, :, 0] > 0.5).sum(1))


def test_a_search_without_the_unseen_vehicles_plans_from_the_dropped_states(highway_worlds):
    _, td = highway_worlds
    roots = td[:4]
    search = bench.RedrawnSearch(
        TensorHighwayEnv(bench.HIGHWAY, num_envs=20), 4, copies=1, redraw="none",
        aggregate="mean", crash_penalty=0.0, seed=0, base="idle", drop_unseen=True,
    )  # fmt: skip
    dropped = roots.clone().set(STATE, bench.without_unseen(roots[STATE], bench.HIGHWAY))
    plain = LookaheadPolicy(
        TensorHighwayEnv(bench.HIGHWAY, num_envs=20), make_scripted_policy("idle"), 4
    )
    assert torch.equal(search.returns(roots), branch_returns(plain.branches(dropped)))


def test_an_observation_to_drop_by_keeps_the_envs_other_config():
    # A world of four lanes, seen by a table of 10 vehicles: the search drops what that
    # table shows of this world, not of the scenario's default three lanes.
    config = {"lanes_count": 4}
    env = TensorHighwayEnv(bench.HIGHWAY, config, num_envs=4, seed=3, return_state=True)
    roots = env.reset()
    table = {"type": "Kinematics", "vehicles_count": 10}
    search = bench.RedrawnSearch(
        TensorHighwayEnv(bench.HIGHWAY, config, num_envs=20), 3, copies=1, redraw="none",
        aggregate="mean", crash_penalty=0.0, seed=0, base="idle", drop_unseen=table,
    )  # fmt: skip
    kept = bench.without_unseen(roots[STATE], bench.HIGHWAY, {**config, "observation": table})
    plain = LookaheadPolicy(
        TensorHighwayEnv(bench.HIGHWAY, config, num_envs=20), make_scripted_policy("idle"), 3
    )
    assert torch.equal(
        search.returns(roots), branch_returns(plain.branches(roots.clone().set(STATE, kept)))
    )


def test_drop_unseen_reads_count_and_behind_and_names_bad_text():
    assert bench.unseen_by(None) is False and bench.unseen_by("") is True
    assert bench.unseen_by("7") == {"type": "Kinematics", "vehicles_count": 7, "see_behind": False}
    assert bench.unseen_by("15,behind")["see_behind"] is True
    for bad in ("abc", "0", "15,ahead", "-3"):
        with pytest.raises(SystemExit, match=f"--drop-unseen '{bad}': give COUNT or COUNT,behind"):
            bench.unseen_by(bad)
