"""How much a scenario leaves to a policy that looks ahead to the episode's end.

On merge-v0 and roundabout-v0 the learners find always-SLOWER (docs/results.md, section
5), on intersection-v0 always-IDLE (section 6). This script asks whether anything beats
always-SLOWER: the test-time search over a scripted
base policy of ``--bases`` (every action tried from the current state, then the base
policy for ``H - 1`` steps, on the tensor simulator from highway-env's state:
:func:`~torchrl_grpo.training.search_eval.evaluate_search`) at each horizon of
``--horizons`` (none: no search), over the same highway-env episodes as always-SLOWER
and paired against it (always-SLOWER is always among the bases). A horizon at least as
long as the episode scores each action with the whole rest of the episode; a shorter one
leaves out what happens after it (merge-v0 pays the slowest car for the most steps).
``--dtypes float64 float32`` also plans in float32, training's dtype, beside the default
float64 (highway-env's: :data:`~torchrl_grpo.training.search_eval.PLAN_DTYPE`), on the
same episodes; a row names its dtype where it is not that default. ``--checkpoints``
adds trained runs (their greedy policies) to the table, and ``--crash-margins`` drives
each of them once per crash margin (``model.crash_margin``: the greedy choice never takes
an action the run's crash head finds likelier to crash than SLOWER by more than it;
``none``: no margin; :class:`~torchrl_grpo.modules.CrashHead`). ``--on tensor`` plays
every row on the tensor simulator from highway-env's starts (as
:func:`~torchrl_grpo.training.transfer.evaluate_on_tensor` does: seconds a policy, where
highway-env takes minutes), in the first of ``--dtypes``.

Printed in one run, one row per policy: return ± standard error, crash rate, mean
speed, the paired difference to always-SLOWER with the verdict of
:func:`~torchrl_grpo.training.results.paired_difference`, and where that difference comes
from: the episodes always-SLOWER crashes in and the others (two shares of the mean that
add up to it, and the others' 5th percentile).

    python benchmarks/lab/bench_scenario_room.py --scenario roundabout-v0 --bases slower idle \\
        --horizons 11 --episodes 1000 --seed 40000 [--dtypes float64 float32]
    python benchmarks/lab/bench_scenario_room.py --scenario roundabout-v0 --bases slower \
        --horizons --on tensor --dtypes float64 --episodes 1000 --seed 60000 \
        --checkpoints <runs' last.pt> --crash-margins none 0.001 0.003 0.01
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

import torchrl_grpo.experimental  # noqa: F401  (runs of algo=grpo_lab load too)
from torchrl_grpo.training import evaluate, load_run_policy, make_env
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.env_builder import make_layout
from torchrl_grpo.training.eval_episodes import eval_workers
from torchrl_grpo.training.evaluation import BASELINE_LABELS, baseline_policy
from torchrl_grpo.training.model_builder import set_crash_margin
from torchrl_grpo.training.results import EvalResult, paired_difference
from torchrl_grpo.training.search_eval import PLAN_DTYPE, evaluate_search
from torchrl_grpo.training.transfer import evaluate_on_tensor

log = logging.getLogger("bench_scenario_room")

# The training config's cap on an episode (conf/env/<scenario>.yaml); merge-v0 ends
# sooner on its own (at x = 370 m), roundabout-v0 after 11 steps, highway-fast-v0 after 30.
MAX_STEPS = 60


#: The table's header: the columns of :func:`table_row`.
TABLE_HEADER = (
    "| policy | return | crash rate | speed (m/s) | paired against always-SLOWER "
    "| of it: always-SLOWER's crashed episodes / the others (their 5th percentile) "
    "| minutes |\n|---|---|---|---|---|---|---|"
)


def with_margin(policy: torch.nn.Module, margin: str) -> torch.nn.Module:
    """``policy`` with its crash heads' margin set to ``margin`` (``"none"``: no margin)."""
    try:
        return set_crash_margin(policy, None if margin == "none" else float(margin))
    except ValueError as err:
        raise SystemExit(f"--crash-margins: {err}") from err


def table_row(res: EvalResult, slower: EvalResult, seconds: float) -> str:
    """One row of the table: ``res``, paired against always-SLOWER's ``slower``."""
    s = res.summary()
    diff, sem, beats = paired_difference(res, slower)
    verdict = f"beats {slower.name}" if beats else f"does not beat {slower.name}"
    # Where the difference comes from: the episodes always-SLOWER crashes in, the others
    # (each share a mean over all episodes, so the two add up), and how the others spread.
    crashed = np.asarray(slower.crashed, dtype=bool)
    rest = diff[~crashed]
    low = f"{np.percentile(rest, 5):+.2f}" if rest.size else "-"
    return (
        f"| {res.name} | {s['return']:.2f} ± {s['return_sem']:.2f} | "
        f"{100 * s['crash_rate']:.1f}% | {s['speed']:.1f} | "
        f"{diff.mean():+.2f} ± {sem:.2f}, {verdict} | "
        f"{diff[crashed].sum() / diff.size:+.2f} / {rest.sum() / diff.size:+.2f} ({low}) | "
        f"{seconds / 60:.1f} |"
    )


def main() -> None:
    """Evaluates always-SLOWER, each base policy and each search, prints the table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--scenario",
        default="roundabout-v0",
        choices=["merge-v0", "roundabout-v0", "intersection-v0", "highway-fast-v0"],
    )
    p.add_argument(
        "--bases",
        nargs="+",
        default=["slower", "idle"],
        choices=list(BASELINE_LABELS),
        help="scripted base policies",
    )
    p.add_argument("--horizons", type=int, nargs="*", default=[8, 30], help="none: no search")
    p.add_argument(
        "--dtypes",
        nargs="+",
        default=None,
        choices=["float64", "float32"],
        help="the planner's float dtypes, a row each (default: PLAN_DTYPE's for --on)",
    )
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=40000, help="seed of the first episode")
    p.add_argument("--workers", type=int, default=None, help="forked processes (default: cores)")
    p.add_argument(
        "--checkpoints", nargs="*", default=[], help="trained runs' last.pt, driven greedily"
    )
    p.add_argument(
        "--crash-margins",
        nargs="*",
        default=[],
        help="drive each checkpoint with each of these model.crash_margin (none: no margin)",
    )
    p.add_argument(
        "--on",
        default="highway",
        choices=["highway", "tensor"],
        help="the episodes: highway-env's, or the tensor simulator's from highway-env's starts",
    )
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    # Trained runs are driven with their own config overrides (their observation, say),
    # and every row of the table on the same env.
    config = {}
    if args.checkpoints:
        config = OmegaConf.create(load_checkpoint(args.checkpoints[0])["config"]).env.config
    env_cfg = OmegaConf.create(
        {"scenario": args.scenario, "config": config, "max_episode_steps": MAX_STEPS}
    )
    env = make_env(env_cfg)
    kw = {"episodes": args.episodes, "seed": args.seed, "max_steps": MAX_STEPS}
    kw["workers"] = eval_workers(args.workers)

    def play(policy, name: str) -> EvalResult:  # noqa: ANN001 (a policy module)
        if args.on == "tensor":
            return evaluate_on_tensor(
                env_cfg, policy, episodes=args.episodes, seed=args.seed, name=name, dtype=dtypes[0]
            )
        return evaluate(env, policy, name=name, **kw)[0]

    dtypes = [getattr(torch, d) for d in args.dtypes or []] or [PLAN_DTYPE[args.on]]
    layout, n_actions = make_layout(env), int(env.action_spec.n)
    results: list[tuple[EvalResult, float]] = []
    if "slower" not in args.bases:  # every row pairs against it
        args.bases.insert(0, "slower")
    for base in args.bases:
        policy, label = baseline_policy(base, layout, n_actions), BASELINE_LABELS[base]
        start = time.perf_counter()
        results.append((play(policy, label), time.perf_counter() - start))
        for horizon in args.horizons:
            for dtype in dtypes:
                start = time.perf_counter()
                name = f"search {horizon} over {label}"
                if dtype != PLAN_DTYPE[args.on]:
                    name += ", " + str(dtype).removeprefix("torch.")
                res = evaluate_search(
                    env_cfg,
                    policy,
                    horizon,
                    name=name,
                    dtype=dtype,
                    on=args.on,
                    **kw,
                )
                results.append((res, time.perf_counter() - start))
                log.info("%s done", name)
    for path in args.checkpoints:
        policy, run = load_run_policy(path, env_cfg, env), str(Path(path).parent.name)
        for margin in args.crash_margins or [None]:
            start = time.perf_counter()
            name = run if margin is None else f"{run}, crash_margin={margin}"
            driven = policy if margin is None else with_margin(policy, margin)
            results.append((play(driven, name), time.perf_counter() - start))
    slower = next(res for res, _ in results if res.name == BASELINE_LABELS["slower"])
    where = "highway-env" if args.on == "highway" else "tensor-simulator"
    print(  # noqa: T201 (the benchmark's output)
        "\n".join(
            [
                f"{args.scenario}: {args.episodes} {where} episodes, seeds "
                f"{args.seed}..{args.seed + args.episodes - 1}",
                "",
                TABLE_HEADER,
                *(table_row(res, slower, sec) for res, sec in results),
            ]
        )
    )


if __name__ == "__main__":
    main()
