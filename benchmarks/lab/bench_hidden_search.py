"""What the observation leaves to a search: plans from redrawn hidden state.

The test-time search (every action tried from the current state, then a base policy)
plans from the simulator's whole state, which holds what no observation shows. A network
that drives from the observation knows no more than a search that does not know it.
This script plays that search: at every decision it copies the state ``--copies``
times, redraws the hidden variables of every vehicle but the ego from the reset's
distribution (``--redraw``), scores each action's branch in every copy as its return
less ``--crash-penalty`` if the branch crashes, and plays the action whose
``--aggregate`` (``mean``: what a risk-neutral learner's target averages; ``min``: the
worst copy) over the copies is highest. ``--redraw none`` is the plain search.

- **roundabout-v0** (``--scenario roundabout-v0``, the default): the branches run to the
  episode's end (11 steps) under ``--bases`` (always-IDLE, or always-SLOWER, whose
  branch says whether braking after the action still avoids a crash). Hidden: each
  other driver's IDM exponent (``delta``, U(3.5, 4.5) at reset) and its destination
  (``route``: one of the three exits, redrawn only for a vehicle on a road from which
  every exit can be reached; on an exit road it is already known), or ``both``.
- **highway-fast-v0**: the branches are 8 steps of ``--base-checkpoint``'s greedy
  policy (the search of ``scripts/evaluate.py search_horizon=8``), or of ``--bases``.
  Hidden: ``delta``; each other driver's target speed (``target``: the speed it was
  spawned at, U(21, 24) m/s, which it returns to in free traffic; drawn from that range
  at or above the car's speed, since IDM never drives a car faster, or from all of it
  with ``--wide-targets``); the clock that times its lane-change decisions (``timer``:
  U(0, 1) s); or ``all`` three. The vehicles the observation leaves out (beyond the
  four nearest, or more than 10 m behind) are kept, unless ``--drop-unseen`` takes them
  away: then the search plans from what the observation shows, with nothing beyond it.
  ``--drop-unseen COUNT[,behind]`` keeps what a Kinematics observation of ``COUNT``
  vehicles (and those behind, with ``see_behind``) shows. A checkpoint's own
  ``env.config`` (its observation) holds for its episodes and branches.

The episodes are the tensor simulator's in float64 from highway-env's starts of
``--seed, --seed + 1, ...`` (the tensor simulator follows highway-env to 1e-9 there:
docs/sim.md), paired against always-SLOWER on the same starts. One row per setting:

    python benchmarks/lab/bench_hidden_search.py --episodes 500 --seed 40000 --copies 8 \\
        --redraw none route both [--aggregate mean min] [--crash-penalty 0 5] \\
        [--bases idle slower]
    python benchmarks/lab/bench_hidden_search.py --scenario highway-fast-v0 \\
        --base-checkpoint <run>/last.pt --episodes 500 --seed 40000 --copies 8 \\
        --redraw none delta target timer all [--wide-targets] [--drop-unseen [COUNT[,behind]]]
"""

from __future__ import annotations

import argparse
import itertools
import logging
import time

import torch
from bench_scenario_room import TABLE_HEADER, table_row  # the table of the scenario's room
from omegaconf import OmegaConf
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.batched_search import search_episodes
from torchrl_grpo.branching.keys import MASK, STATE
from torchrl_grpo.branching.lookahead import branch_returns
from torchrl_grpo.branching.rollout import branch_rollout
from torchrl_grpo.branching.root_builders import as_roots
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY
from torchrl_grpo.modules import make_scripted_policy
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.roundabout_reset import route_paths
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.evaluation import BASELINE_LABELS
from torchrl_grpo.training.pretrained import load_run_policy
from torchrl_grpo.training.results import EvalResult
from torchrl_grpo.training.search_eval import searched_result
from torchrl_grpo.training.transfer import evaluate_on_tensor

log = logging.getLogger("bench_hidden_search")

SCENARIO = "roundabout-v0"
# roundabout-v0 ends after 11 steps: a branch of 11 steps scores the rest of the episode.
HORIZON = 11
REDRAWS = ("none", "delta", "route", "both")
# highway-fast-v0: the test-time search's 8 steps, in episodes of at most 30.
HIGHWAY = "highway-fast-v0"
HIGHWAY_HORIZON, HIGHWAY_STEPS = 8, 30
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
        >>> state = env.reset()[STATE]
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


class RedrawnSearch(LookaheadPolicy):
    """The lookahead planner, scoring each action over copies with redrawn hidden state.

    Each branch is the action, then the ``base`` policy: a scripted policy's name
    (``"idle"``, ``"slower"``) or a trained actor, which acts greedily.

    ``returns`` gives ``[N, n_actions]``: per action, the ``aggregate`` over ``copies``
    redraws of its branch return less ``crash_penalty`` where the branch crashes. Its
    env needs ``N * copies * n_actions`` rows. ``drop_unseen``: True plans from what the
    env's own observation shows (:func:`without_unseen`); an observation config, from
    what that one shows.
    """

    def __init__(
        self,
        env: TensorHighwayEnv,
        horizon: int,
        *,
        copies: int,
        redraw: str,
        aggregate: str,
        crash_penalty: float,
        seed: int,
        base: str | TensorDictModuleBase = "idle",
        wide_targets: bool = False,
        drop_unseen: dict | bool = False,
    ) -> None:
        if isinstance(base, str):
            base = make_scripted_policy(base)
        else:
            base = DeterministicActor(base)
        super().__init__(env, base, horizon)
        if aggregate not in ("mean", "min"):
            raise ValueError(f"aggregate must be 'mean' or 'min', got {aggregate!r}")
        self.copies, self.redraw, self.aggregate = int(copies), redraw, aggregate
        self.crash_penalty = float(crash_penalty)
        self.draws = torch.Generator().manual_seed(seed)
        self.wide_targets = wide_targets
        self.drop_unseen = drop_unseen

    def returns(self, tensordict: TensorDictBase) -> torch.Tensor:
        return self.outcomes(tensordict)[0]

    def outcomes(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``[N, n_actions]``: the aggregated scores, and the share of copies that crash."""
        state = tensordict.get(STATE)
        if self.drop_unseen is not False:
            # True: what this env's own observation (its config's, else the scenario's)
            # shows; an observation: what it shows of the same world (the env's config).
            own = self.drop_unseen is True
            seen_by = self.env.overrides
            if not own:
                seen_by = {**seen_by, "observation": self.drop_unseen}
            state = without_unseen(state, self.env.scenario, seen_by)
        n = state.shape[0]
        state = state.unsqueeze(1).expand(n, self.copies).reshape(n * self.copies)
        state = redraw_hidden(state, self.env.params, self.redraw, self.draws, self.wide_targets)
        data = branch_rollout(
            self.env, self._branch_policy, as_roots(state), self.n_actions, self.horizon
        )
        mask = data.get(MASK)
        self.frames += int(mask.sum())
        crashed = (data.get(("next", "crashed")).reshape(mask.shape) & mask).any(-1)
        scores = branch_returns(data) - self.crash_penalty * crashed.double()
        scores = scores.reshape(n, self.copies, self.n_actions)
        crash_share = crashed.double().reshape(n, self.copies, self.n_actions).mean(1)
        return (scores.mean(1) if self.aggregate == "mean" else scores.amin(1)), crash_share


def play(planner: RedrawnSearch, seeds: list[int], name: str, max_steps: int) -> EvalResult:
    """The planner's episodes of ``seeds`` on the float64 tensor simulator."""
    episodes = TensorHighwayEnv(
        planner.env.scenario, planner.env.overrides, num_envs=len(seeds), return_state=True,
        dtype=torch.float64,
    )  # fmt: skip
    return searched_result(name, search_episodes(planner, episodes, seeds, max_steps), seeds)


def main() -> None:
    """Plays always-SLOWER and each setting's search; prints the table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", choices=(SCENARIO, HIGHWAY), default=SCENARIO)
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--seed", type=int, default=40_000, help="the first episode's seed")
    p.add_argument("--copies", type=int, default=8, help="redraws per decision")
    p.add_argument(
        "--redraw", nargs="+", choices=sorted(set(REDRAWS + HIGHWAY_REDRAWS)),
        default=["none", "route", "both"],
    )  # fmt: skip
    p.add_argument("--aggregate", nargs="+", choices=("mean", "min"), default=["mean"])
    p.add_argument("--crash-penalty", nargs="+", type=float, default=[0.0])
    p.add_argument(
        "--bases", nargs="+", choices=("idle", "slower"), default=["idle"],
        help="the branches' policy after their first action",
    )  # fmt: skip
    p.add_argument(
        "--wide-targets", action="store_true",
        help="highway-fast-v0: target speeds from the whole spawn range U(21, 24)",
    )  # fmt: skip
    p.add_argument(
        "--drop-unseen", nargs="?", const="", default=None, metavar="COUNT[,behind]",
        help="plan from the states without the vehicles the observation leaves out; with "
        "COUNT, those a Kinematics observation of COUNT vehicles leaves out (',behind': "
        "with see_behind)",
    )  # fmt: skip
    p.add_argument(
        "--base-checkpoint", default=None,
        help="a run's last.pt whose greedy policy the branches follow instead of --bases",
    )  # fmt: skip
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    roundabout = args.scenario == SCENARIO
    kinds = REDRAWS if roundabout else HIGHWAY_REDRAWS
    if bad := [r for r in args.redraw if r not in kinds]:
        raise SystemExit(f"--redraw {' '.join(bad)}: {args.scenario} redraws {kinds}")
    horizon, max_steps = (HORIZON, HORIZON) if roundabout else (HIGHWAY_HORIZON, HIGHWAY_STEPS)
    seeds = list(range(args.seed, args.seed + args.episodes))
    cfg = OmegaConf.create({"scenario": args.scenario, "config": {}})
    bases: list = list(args.bases)
    if args.base_checkpoint is not None:
        env_cfg = OmegaConf.create(load_checkpoint(args.base_checkpoint)["config"]["env"])
        if env_cfg.scenario != args.scenario:
            raise SystemExit(f"--base-checkpoint: a run of {env_cfg.scenario}, not {args.scenario}")
        cfg = env_cfg
        probe = TensorHighwayEnv(args.scenario, env_overrides(env_cfg), num_envs=1)
        bases = [load_run_policy(args.base_checkpoint, env_cfg, probe)]
    start = time.perf_counter()
    slower = evaluate_on_tensor(
        cfg, make_scripted_policy("slower"), episodes=args.episodes, seed=args.seed,
        name="always-SLOWER", dtype=torch.float64,
    )  # fmt: skip
    rows = [table_row(slower, slower, time.perf_counter() - start)]
    if args.base_checkpoint is not None:
        start = time.perf_counter()
        greedy = evaluate_on_tensor(
            cfg, bases[0], episodes=args.episodes, seed=args.seed,
            name=f"{args.base_checkpoint}, greedy", dtype=torch.float64,
        )  # fmt: skip
        rows.append(table_row(greedy, slower, time.perf_counter() - start))
    drop_unseen: dict | bool = False
    seen_by = "the observation"
    if args.drop_unseen:  # COUNT[,behind]
        count, _, behind = args.drop_unseen.partition(",")
        drop_unseen = {"type": "Kinematics", "vehicles_count": int(count)}
        drop_unseen["see_behind"] = behind == "behind"
        seen_by = f"an observation of {count} vehicles" + (" and those behind" * bool(behind))
    elif args.drop_unseen is not None:
        drop_unseen = True
    settings = itertools.product(bases, args.redraw, args.aggregate, args.crash_penalty)
    for base, redraw, aggregate, penalty in settings:
        # The plain search needs one copy: every copy would be the same state.
        copies = 1 if redraw == "none" else args.copies
        rows_needed = args.episodes * copies * 5
        env = TensorHighwayEnv(
            args.scenario, env_overrides(cfg), num_envs=rows_needed, dtype=torch.float64
        )
        planner = RedrawnSearch(
            env, horizon, copies=copies, redraw=redraw, aggregate=aggregate,
            crash_penalty=penalty, seed=args.seed, base=base, wide_targets=args.wide_targets,
            drop_unseen=drop_unseen,
        )  # fmt: skip
        name = f"redraw {redraw}, {copies} copies, {aggregate}, crash penalty {penalty:g}"
        if args.wide_targets and redraw in ("target", "all"):
            name += ", wide targets"
        if args.drop_unseen is not None:
            name += f", the vehicles {seen_by} leaves out dropped"
        if not isinstance(base, str):
            name = f"H={horizon} over the checkpoint, {name}"
        elif base != "idle":
            name = f"over {BASELINE_LABELS[base]}, {name}"
        start = time.perf_counter()
        res = play(planner, seeds, name, max_steps)
        rows.append(table_row(res, slower, time.perf_counter() - start))
        log.info("played: %s", name)
    log.info(
        "\n%s: %d tensor-simulator episodes (float64) from highway-env's starts, seeds %d..%d"
        "\n\n%s\n%s",
        args.scenario, args.episodes, seeds[0], seeds[-1], TABLE_HEADER, "\n".join(rows),
    )  # fmt: skip


if __name__ == "__main__":
    main()
