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
from hidden_state import (
    HIGHWAY,
    HIGHWAY_REDRAWS,
    REDRAWS,
    SCENARIO,
    redraw_hidden,
    without_unseen,
)
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.batched_search import search_episodes
from torchrl_grpo.branching.keys import MASK, STATE
from torchrl_grpo.branching.lookahead import branch_returns
from torchrl_grpo.branching.rollout import branch_rollout
from torchrl_grpo.branching.root_builders import as_roots
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import make_scripted_policy
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.evaluation import BASELINE_LABELS
from torchrl_grpo.training.pretrained import load_run_policy
from torchrl_grpo.training.results import EvalResult
from torchrl_grpo.training.search_eval import searched_result
from torchrl_grpo.training.transfer import evaluate_on_tensor

log = logging.getLogger("bench_hidden_search")
# roundabout-v0 ends after 11 steps: a branch of 11 steps scores the rest of the episode;
# highway-fast-v0: the test-time search's 8 steps, in episodes of at most 30.
HORIZON, HIGHWAY_HORIZON, HIGHWAY_STEPS = 11, 8, 30


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


def unseen_by(text: str | None) -> dict | bool:
    """``--drop-unseen``: False (absent), True (bare: the env's own observation), or the
    Kinematics observation of ``COUNT[,behind]``.

    Raises:
        SystemExit: text that is not ``COUNT`` or ``COUNT,behind`` with a positive count.

    Example:
        >>> unseen_by("15,behind")
        {'type': 'Kinematics', 'vehicles_count': 15, 'see_behind': True}
    """
    if text is None:
        return False
    if text == "":
        return True
    count, _, behind = text.partition(",")
    if not count.isdigit() or int(count) < 1 or behind not in ("", "behind"):
        raise SystemExit(
            f"--drop-unseen {text!r}: give COUNT or COUNT,behind, a positive vehicle count "
            "(such as 15 or 15,behind)"
        )
    return {"type": "Kinematics", "vehicles_count": int(count), "see_behind": bool(behind)}


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
    drop_unseen = unseen_by(args.drop_unseen)
    seen_by = "the observation"
    if isinstance(drop_unseen, dict):
        seen_by = f"an observation of {drop_unseen['vehicles_count']} vehicles"
        seen_by += " and those behind" * drop_unseen["see_behind"]
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
