"""What a search knows that the observation does not: redrawn hidden state, unseen vehicles.

The helpers of ``bench_hidden_search.py`` (and ``bench_crash_causes.py``):
:func:`redraw_hidden` draws the other drivers' hidden variables afresh from the reset's
distribution; :func:`observed_vehicles` and :func:`without_unseen` find and drop the
vehicles an observation leaves out.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.roundabout_reset import route_paths

SCENARIO, HIGHWAY = "roundabout-v0", "highway-fast-v0"
#: What each scenario's search can redraw.
REDRAWS = ("none", "delta", "route", "both")
HIGHWAY_REDRAWS = ("none", "delta", "target", "timer", "all")


def _fresh_others(
    column: torch.Tensor, low: float, high: float, generator: torch.Generator
) -> torch.Tensor:
    """``column`` [N, V] with every vehicle but the ego (column 0) drawn from U(low, high)."""
    n, count = column.shape
    fresh = low + (high - low) * torch.rand(n, count - 1, generator=generator)
    return torch.cat([column[:, :1], fresh.to(column.dtype)], 1)


def redraw_hidden(
    state: TensorDictBase,
    params: RoundaboutParams | HighwayParams,
    redraw: str,
    generator: torch.Generator,
    wide_targets: bool = False,
) -> TensorDictBase:
    """A copy of ``state`` with the other vehicles' hidden variables drawn afresh.

    Args:
        state: roundabout-v0 or highway-fast-v0 states ``[N]`` of the tensor simulator
            (``return_state=True``).
        params: the scenario's constants (``TensorHighwayEnv.params``), which also tell
            the scenario.
        redraw: roundabout-v0: ``"none"``, ``"delta"`` (IDM exponents), ``"route"``
            (destinations, for vehicles on a road from which every exit is reachable)
            or ``"both"``; highway-fast-v0: ``"none"``, ``"delta"``, ``"target"`` (the
            target speeds), ``"timer"`` (the lane-change clocks) or ``"all"``.
        generator: the draws' random stream.
        wide_targets: highway-fast-v0: draw the target speeds from the whole spawn
            range, not only at or above each car's speed (knowing less than the
            observation shows).

    Returns:
        The new states; the ego (vehicle 0) and everything the observation shows are
        unchanged.

    Example:
        >>> env = TensorHighwayEnv(SCENARIO, num_envs=2, return_state=True)
        >>> state = env.reset()["state"]
        >>> same = redraw_hidden(state, env.params, "none", torch.Generator())
        >>> bool((same == state).all())
        True
    """
    roundabout = isinstance(params, RoundaboutParams)
    if not roundabout and not isinstance(params, HighwayParams):
        raise ValueError(f"redraws are for {SCENARIO} and {HIGHWAY}, not {type(params).__name__}")
    kinds = REDRAWS if roundabout else HIGHWAY_REDRAWS
    if redraw not in kinds:
        raise ValueError(f"redraw must be one of {kinds}, got {redraw!r}")
    state = state.clone()
    vehicles = state["vehicles"]
    if redraw in ("delta", "both", "all"):
        # The reset's draw of an IDM exponent (highway-env's IDMVehicle.randomize_behavior).
        vehicles["delta"] = _fresh_others(vehicles["delta"], *params.idm.delta_range, generator)
    if not roundabout:
        if redraw in ("target", "all"):
            # create_random's speed U(low, high), which IDMVehicle keeps as its target
            # speed, given what the observation shows: IDM never drives a car faster
            # than its target speed, so the target is at least the car's speed.
            limit, traffic = params.road.speed_limit, params.traffic
            low, high = traffic.speed_low * limit, traffic.speed_high * limit
            target = vehicles["target_speed"]
            if wide_targets:
                vehicles["target_speed"] = _fresh_others(target, low, high, generator)
            else:
                least = vehicles["speed"][:, 1:].clamp(low, high)
                u = torch.rand(least.shape, generator=generator).to(target.dtype)
                fresh = least + (high - least) * u
                vehicles["target_speed"] = torch.cat([target[:, :1], fresh], 1)
        if redraw in ("timer", "all"):
            # A lane-change decision falls due each time the timer passes the delay.
            delay = params.idm.lane_change_delay
            vehicles["timer"] = _fresh_others(vehicles["timer"], 0.0, delay, generator)
        return state
    if redraw in ("route", "both"):
        n, count = vehicles["x"].shape
        paths = route_paths(params, torch.device("cpu"))
        exits = torch.tensor(params.traffic.destinations)
        reachable = (paths[:, exits, 0] >= 0).all(-1)  # roads from which every exit is
        lane = vehicles["lane"]
        road = torch.tensor(params.road.road)[lane]
        goal = exits[torch.randint(0, len(exits), (n, count), generator=generator)]
        legs = torch.cat([lane.unsqueeze(-1), paths[road, goal]], -1)
        redo = reachable[road]
        redo[:, 0] = False
        # As the reset encodes a route: the car's lane, then the path from its road, from
        # the start (head 0); the tests check that this drives as the original encoding.
        old_legs, old_head = state["route", "legs"], state["route", "head"]
        state["route", "legs"] = torch.where(redo.unsqueeze(-1), legs, old_legs)
        state["route", "head"] = torch.where(redo, torch.zeros_like(old_head), old_head)
    return state


@torch.no_grad()
def observed_vehicles(
    state: TensorDictBase, scenario: str, config: dict | None = None
) -> torch.Tensor:
    """Which vehicles of each state the ego's observation shows: ``[n, count]`` booleans.

    A vehicle is observed exactly when taking it out of the world changes the
    observation; one the table leaves out changes nothing. The ego counts as observed.
    ``config``: the overrides whose observation is meant (default: the scenario's own).
    """
    n, count = state.get(("vehicles", "present")).shape
    rows = state.unsqueeze(1).expand(n, count).reshape(n * count).clone()
    present = rows.get(("vehicles", "present")).reshape(n, count, count)
    others = torch.arange(1, count)
    present[:, others, others] = False  # row j of a state: vehicle j taken out
    rows.set(("vehicles", "present"), present.reshape(n * count, count))
    dtype = state.get(("vehicles", "x")).dtype
    env = TensorHighwayEnv(scenario, config, num_envs=n * count, dtype=dtype)
    # The same world under another observation: the state is stamped with its config.
    rows.set("fingerprint", torch.full_like(rows.get("fingerprint"), env.fingerprint))
    obs = env.reset(TensorDict({STATE_KEY: rows}, batch_size=[n * count]), set_state=True)
    obs = obs.get("observation").reshape(n, count, -1)
    seen = (obs[:, 1:] != obs[:, :1]).any(-1)
    return torch.cat([torch.ones(n, 1, dtype=torch.bool), seen], 1)


def without_unseen(
    state: TensorDictBase, scenario: str, config: dict | None = None
) -> TensorDictBase:
    """The states with every vehicle that the observation of ``config`` leaves out made
    absent, as the padding rows are (:func:`observed_vehicles`)."""
    out = state.clone()
    present = out.get(("vehicles", "present"))
    out.set(("vehicles", "present"), present & observed_vehicles(state, scenario, config))
    return out
