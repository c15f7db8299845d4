"""What the observation leaves to a search on roundabout-v0: plans from redrawn hidden state.

The search over always-IDLE to the episode's end drives roundabout-v0 at 10.86 with no
crash in 1,000 highway-env episodes (docs/lab/scenarios.md), but it plans from the
simulator's whole state. Two things in that state no observation shows: each other
driver's IDM exponent (``delta``, drawn from U(3.5, 4.5) at reset) and its destination
(one of the three exits, drawn uniformly). A network that drives from the observation
knows no more than a search that does not know them. This script plays that search:
at every decision it copies the state ``--copies`` times, redraws the hidden variables
of every vehicle but the ego from the reset's distribution (``--redraw``: ``delta``,
``route``, ``both``, or ``none`` for the plain search), scores each action's branch (the
action, then the base policy of ``--bases`` to the episode's end: always-IDLE, or
always-SLOWER, whose branch says whether braking after the action still avoids a crash)
in every copy as its return less ``--crash-penalty`` if the branch crashes, and plays
the action whose ``--aggregate`` (``mean``: what a risk-neutral learner's target
averages; ``min``: the worst copy) over the copies is highest. A destination is redrawn
only for a vehicle on a road from which every exit can be reached; on an exit road it is
already known.

The episodes are the tensor simulator's in float64 from highway-env's starts of
``--seed, --seed + 1, ...`` (the tensor simulator follows highway-env to 1e-9 there:
docs/sim.md), paired against always-SLOWER on the same starts. One row per setting:

    python benchmarks/lab/bench_hidden_search.py --episodes 500 --seed 40000 --copies 8 \\
        --redraw none route both [--aggregate mean min] [--crash-penalty 0 5] \\
        [--bases idle slower]
"""

from __future__ import annotations

import argparse
import itertools
import logging
import time

import torch
from bench_scenario_room import TABLE_HEADER, table_row  # the table of the scenario's room
from omegaconf import OmegaConf
from tensordict import TensorDictBase

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.batched_search import search_episodes
from torchrl_grpo.branching.keys import MASK, STATE
from torchrl_grpo.branching.lookahead import branch_returns
from torchrl_grpo.branching.rollout import branch_rollout
from torchrl_grpo.branching.root_builders import as_roots
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import make_scripted_policy
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.roundabout_reset import route_paths
from torchrl_grpo.training.evaluation import BASELINE_LABELS
from torchrl_grpo.training.results import EvalResult
from torchrl_grpo.training.search_eval import searched_result
from torchrl_grpo.training.transfer import evaluate_on_tensor

log = logging.getLogger("bench_hidden_search")

SCENARIO = "roundabout-v0"
# roundabout-v0 ends after 11 steps: a branch of 11 steps scores the rest of the episode.
HORIZON = 11
REDRAWS = ("none", "delta", "route", "both")


def redraw_hidden(
    state: TensorDictBase, params: RoundaboutParams, redraw: str, generator: torch.Generator
) -> TensorDictBase:
    """A copy of ``state`` with the other vehicles' hidden variables drawn afresh.

    Args:
        state: roundabout states ``[N]`` of the tensor simulator (``return_state=True``).
        params: the scenario's constants (``TensorHighwayEnv.params``).
        redraw: ``"none"``, ``"delta"`` (IDM exponents), ``"route"`` (destinations, for
            vehicles on a road from which every exit is reachable) or ``"both"``.
        generator: the draws' random stream.

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
    if redraw not in REDRAWS:
        raise ValueError(f"redraw must be one of {REDRAWS}, got {redraw!r}")
    state = state.clone()
    vehicles = state["vehicles"]
    n, count = vehicles["x"].shape
    if redraw in ("delta", "both"):
        # The reset's draw of an IDM exponent (highway-env's IDMVehicle.randomize_behavior).
        delta = vehicles["delta"]
        low, high = params.idm.delta_range
        fresh = low + (high - low) * torch.rand(n, count - 1, generator=generator)
        vehicles["delta"] = torch.cat([delta[:, :1], fresh.to(delta.dtype)], 1)
    if redraw in ("route", "both"):
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


class RedrawnSearch(LookaheadPolicy):
    """The lookahead planner, scoring each action over copies with redrawn hidden state.

    Each branch is the action, then the scripted ``base`` policy (``"idle"``, ``"slower"``).

    ``returns`` gives ``[N, n_actions]``: per action, the ``aggregate`` over ``copies``
    redraws of its branch return less ``crash_penalty`` where the branch crashes. Its
    env needs ``N * copies * n_actions`` rows.
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
        base: str = "idle",
    ) -> None:
        super().__init__(env, make_scripted_policy(base), horizon)
        if aggregate not in ("mean", "min"):
            raise ValueError(f"aggregate must be 'mean' or 'min', got {aggregate!r}")
        self.copies, self.redraw, self.aggregate = int(copies), redraw, aggregate
        self.crash_penalty = float(crash_penalty)
        self.draws = torch.Generator().manual_seed(seed)

    def returns(self, tensordict: TensorDictBase) -> torch.Tensor:
        state = tensordict.get(STATE)
        n = state.shape[0]
        state = state.unsqueeze(1).expand(n, self.copies).reshape(n * self.copies)
        state = redraw_hidden(state, self.env.params, self.redraw, self.draws)
        data = branch_rollout(
            self.env, self._branch_policy, as_roots(state), self.n_actions, self.horizon
        )
        mask = data.get(MASK)
        self.frames += int(mask.sum())
        crashed = (data.get(("next", "crashed")).reshape(mask.shape) & mask).any(-1)
        scores = branch_returns(data) - self.crash_penalty * crashed.double()
        scores = scores.reshape(n, self.copies, self.n_actions)
        return scores.mean(1) if self.aggregate == "mean" else scores.amin(1)


def play(planner: RedrawnSearch, seeds: list[int], name: str) -> EvalResult:
    """The planner's episodes of ``seeds`` on the float64 tensor simulator."""
    episodes = TensorHighwayEnv(
        SCENARIO, num_envs=len(seeds), return_state=True, dtype=torch.float64
    )
    return searched_result(name, search_episodes(planner, episodes, seeds, HORIZON), seeds)


def main() -> None:
    """Plays always-SLOWER and each setting's search; prints the table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--seed", type=int, default=40_000, help="the first episode's seed")
    p.add_argument("--copies", type=int, default=8, help="redraws per decision")
    p.add_argument("--redraw", nargs="+", choices=REDRAWS, default=["none", "route", "both"])
    p.add_argument("--aggregate", nargs="+", choices=("mean", "min"), default=["mean"])
    p.add_argument("--crash-penalty", nargs="+", type=float, default=[0.0])
    p.add_argument(
        "--bases", nargs="+", choices=("idle", "slower"), default=["idle"],
        help="the branches' policy after their first action",
    )  # fmt: skip
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    seeds = list(range(args.seed, args.seed + args.episodes))
    cfg = OmegaConf.create({"scenario": SCENARIO, "config": {}})
    start = time.perf_counter()
    slower = evaluate_on_tensor(
        cfg, make_scripted_policy("slower"), episodes=args.episodes, seed=args.seed,
        name="always-SLOWER", dtype=torch.float64,
    )  # fmt: skip
    rows = [table_row(slower, slower, time.perf_counter() - start)]
    settings = itertools.product(args.bases, args.redraw, args.aggregate, args.crash_penalty)
    for base, redraw, aggregate, penalty in settings:
        # The plain search needs one copy: every copy would be the same state.
        copies = 1 if redraw == "none" else args.copies
        rows_needed = args.episodes * copies * 5
        env = TensorHighwayEnv(SCENARIO, num_envs=rows_needed, dtype=torch.float64)
        planner = RedrawnSearch(
            env, HORIZON, copies=copies, redraw=redraw, aggregate=aggregate,
            crash_penalty=penalty, seed=args.seed, base=base,
        )  # fmt: skip
        name = f"redraw {redraw}, {copies} copies, {aggregate}, crash penalty {penalty:g}"
        if base != "idle":
            name = f"over {BASELINE_LABELS[base]}, {name}"
        start = time.perf_counter()
        res = play(planner, seeds, name)
        rows.append(table_row(res, slower, time.perf_counter() - start))
        log.info("played: %s", name)
    log.info(
        "\n%s: %d tensor-simulator episodes (float64) from highway-env's starts, seeds %d..%d"
        "\n\n%s\n%s",
        SCENARIO, args.episodes, seeds[0], seeds[-1], TABLE_HEADER, "\n".join(rows),
    )  # fmt: skip


if __name__ == "__main__":
    main()
