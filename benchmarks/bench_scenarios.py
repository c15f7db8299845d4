"""Trained runs of one scenario against its baselines, paired on held-out highway-env episodes.

Trains nothing: give the folders of finished runs (``scripts/train.py env=<env> ...``),
GRPO's and PPO's, one per seed, in seed order. Every policy drives the same ``--episodes``
highway-env episodes from ``--seed`` on (seeds that no run evaluated or selected on:
training evaluates on 10000.. and 20000..). Printed, in one run:

* one row per policy: return (mean ± standard error), crash rate, and the same episodes
  replayed on the tensor simulator (:func:`~torchrl_grpo.training.transfer.evaluate_on_tensor`,
  the worlds imported from highway-env; in float32 as training runs, or
  ``--tensor-dtype float64``) with the transfer gap, highway-env minus tensor;
* for each seed, GRPO paired against always-SLOWER, the rule policy (intersection-v0,
  whose actions are longitudinal only: always-IDLE) and PPO of that seed
  ("beats": a mean return higher by more than two standard errors of the per-episode
  difference, and a crash rate no higher);
* each run's training minutes and frames.

``--crash-margin m`` drives the GRPO runs at the crash margin ``m`` (``none``: without
one) instead of their own ``model.crash_margin``: the margin acts only on the greedy
choice (:func:`~torchrl_grpo.training.model_builder.set_crash_margin`), so one training
run can be driven at the margin chosen on other episodes.

With ``--search-horizon H``, also the test-time search over always-SLOWER and over each
GRPO run (every action tried, then ``H - 1`` greedy steps of that policy, on the tensor
simulator from the highway-env state:
:func:`~torchrl_grpo.training.search_eval.evaluate_search`), on the same highway-env
episodes, each paired against the policy it searches over: what the scenario allows a
policy that looks ahead, and how far the learner trails it.

Each policy's episodes are kept in ``--out`` (one JSON file per policy, run and seed set,
the run named by its folder and a digest of its checkpoint; runs trained with config
overrides, such as another observation, in a folder of that config's own), so an
interrupted run picks up where it stopped.

    python benchmarks/bench_scenarios.py --grpo runs/merge_grpo_s0 runs/merge_grpo_s1 \\
        runs/merge_grpo_s2 --ppo runs/merge_ppo_s0 runs/merge_ppo_s1 runs/merge_ppo_s2 \\
        --episodes 1000 --seed 40000 [--search-horizon 8] [--crash-margin 0.01]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
from pathlib import Path

import torch
from omegaconf import OmegaConf

import torchrl_grpo.experimental  # noqa: F401  (runs of algo=grpo_lab load too)
from torchrl_grpo.training import evaluate, load_checkpoint, load_run_policy, make_env
from torchrl_grpo.training.baseline_cache import read_cached, write_cached
from torchrl_grpo.training.config import typed_config
from torchrl_grpo.training.env_builder import make_layout
from torchrl_grpo.training.eval_episodes import eval_workers
from torchrl_grpo.training.evaluation import BASELINE_LABELS, baseline_policy
from torchrl_grpo.training.model_builder import set_crash_margin
from torchrl_grpo.training.results import EvalResult, compare_paired, paired_difference
from torchrl_grpo.training.search_eval import evaluate_search
from torchrl_grpo.training.transfer import evaluate_on_tensor, paired_gap


def _cached(out: Path, name: str, source: str, seed: int, episodes: int, run) -> EvalResult:
    # One file per policy and seed set: a rerun after an interruption skips what is done.
    # A trained policy's file names its run too (``source``, :func:`run_key`): two runs of
    # the same algorithm and seed (another config) must not share results.
    key = f"{name} {source}" if source else name
    path = out / f"{key.replace(' ', '_')}_{seed}_{episodes}.json"
    result = read_cached(path)
    if result is None:
        result = run()
        result.name = name
        write_cached(path, result)
    return result


def run_key(run: Path) -> str:
    """What names a trained run's cached results: its folder and a digest of its checkpoint.

    The folder alone is not enough: two runs of the same name in other places (a rerun
    with more frames, a copy with another margin) would share one run's episodes.
    """
    digest = hashlib.sha1((run / "last.pt").read_bytes()).hexdigest()[:10]
    return f"{run.name}_{digest}"


def parse_margin(text: str) -> float | None:
    """``--crash-margin``'s value: a probability in ``[0, 1]``, or ``none``."""
    if text == "none":
        return None
    try:
        margin = float(text)
    except ValueError:
        margin = float("nan")
    if not 0 <= margin <= 1:
        raise argparse.ArgumentTypeError(f"a probability in [0, 1] or 'none', got {text!r}")
    return margin


def _row(res: EvalResult, tensor: EvalResult | None) -> str:
    s = res.summary()
    cells = [
        res.name,
        f"{s['return']:.2f} ± {s['return_sem']:.2f}",
        f"{100 * s['crash_rate']:.1f}%",
    ]
    if tensor is None:
        cells += ["-", "-"]
    else:
        t, gap = tensor.summary(), paired_gap(res, tensor)
        cells += [
            f"{t['return']:.2f} / {100 * t['crash_rate']:.1f}%",
            f"{gap['return_gap']:+.3f} ± {gap['return_gap_sem']:.3f}, "
            f"{100 * gap['crash_gap']:+.1f}%",
        ]
    return "| " + " | ".join(cells) + " |"


def _training(run: Path) -> str:
    rows = [json.loads(line) for line in (run / "eval_history.jsonl").read_text().splitlines()]
    final = rows[-1]
    return f"{run.name}: {final['frames']:,} frames in {final['wall_seconds'] / 60:.1f} min"


def main() -> None:
    """Evaluates the runs and the baselines, prints the tables."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grpo", type=Path, nargs="+", required=True, help="GRPO run folders")
    p.add_argument("--ppo", type=Path, nargs="+", required=True, help="PPO run folders")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=40000, help="seed of the first episode")
    p.add_argument("--workers", type=int, default=None, help="forked processes (default: cores)")
    p.add_argument("--out", type=Path, default=Path("outputs/bench_scenarios"))
    p.add_argument(
        "--tensor-dtype",
        choices=["float32", "float64"],
        default="float32",
        help="the tensor simulator's dtype for the replay (float64: no float32 rounding)",
    )
    p.add_argument(
        "--search-horizon",
        type=int,
        default=0,
        help="> 0: also the test-time search over always-SLOWER and each GRPO run, this many steps",
    )
    p.add_argument(
        "--crash-margin",
        type=parse_margin,
        default=argparse.SUPPRESS,
        help="drive the GRPO runs at this model.crash_margin ('none': without one); "
        "default: each run's own",
    )
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if len(args.grpo) != len(args.ppo):
        raise SystemExit("give one PPO run per GRPO run (the same seeds, in the same order)")
    env_cfg = typed_config(load_checkpoint(args.grpo[0] / "last.pt")["config"]).env
    out = args.out / str(env_cfg.scenario)
    if env_cfg.config:  # the baselines' results hold for one config: a folder per config
        overrides = json.dumps(OmegaConf.to_container(env_cfg.config), sort_keys=True)
        out = out / f"config_{hashlib.sha1(overrides.encode()).hexdigest()[:10]}"
    out.mkdir(parents=True, exist_ok=True)
    env = make_env(env_cfg)
    steps = int(env_cfg.max_episode_steps)
    kw = {"episodes": args.episodes, "seed": args.seed, "max_steps": steps, "progress": True}
    kw["workers"] = eval_workers(args.workers)

    def run_policy(name: str, source: str, policy) -> EvalResult:
        return _cached(
            out, name, source, args.seed, args.episodes, lambda: evaluate(env, policy, **kw)[0]
        )

    dtype = getattr(torch, args.tensor_dtype)
    suffix = " tensor" if dtype == torch.float32 else f" tensor {args.tensor_dtype}"

    def run_tensor(name: str, source: str, policy) -> EvalResult:
        return _cached(
            out,
            name + suffix,
            source,
            args.seed,
            args.episodes,
            lambda: evaluate_on_tensor(
                env_cfg, policy, episodes=args.episodes, seed=args.seed, dtype=dtype
            ),
        )

    def run_search(name: str, source: str, policy) -> EvalResult:
        label = f"search {args.search_horizon} over {name}"
        return _cached(
            out,
            label,
            source,
            args.seed,
            args.episodes,
            lambda: evaluate_search(
                env_cfg,
                policy,
                args.search_horizon,
                name=label,
                **kw,  # highway-env episodes
            ),
        )

    layout, n_actions = make_layout(env), int(env.action_spec.n)
    searched: list[tuple[EvalResult, EvalResult]] = []
    rows: list[tuple[EvalResult, EvalResult | None]] = []
    scripted = {}
    # The rule policy changes lanes; intersection-v0 (3 longitudinal actions) has always-IDLE.
    baselines = ("slower", "rule") if n_actions == 5 else ("slower", "idle")
    for name in baselines:
        policy = baseline_policy(name, layout, n_actions)
        scripted[name] = run_policy(BASELINE_LABELS[name], "", policy)
        rows.append((scripted[name], None))
    trained: dict[str, list[EvalResult]] = {"grpo": [], "ppo": []}
    for algo, runs in (("grpo", args.grpo), ("ppo", args.ppo)):
        for run in runs:
            seed = int(typed_config(load_checkpoint(run / "last.pt")["config"]).seed)
            policy = load_run_policy(str(run / "last.pt"), env_cfg, env)
            name = f"{algo} seed {seed}"
            key = run_key(run)
            if algo == "grpo" and hasattr(args, "crash_margin"):
                try:
                    set_crash_margin(policy, args.crash_margin)
                except ValueError as err:
                    raise SystemExit(f"--crash-margin: {run}: {err}") from err
                # The name, part of the cached file's, keeps two margins' episodes apart.
                name += f", crash_margin={args.crash_margin}"
            res = run_policy(name, key, policy)
            trained[algo].append(res)
            rows.append((res, run_tensor(name, key, policy)))
            if algo == "grpo" and args.search_horizon > 0:
                searched.append((res, run_search(name, key, policy)))
    if args.search_horizon > 0:
        slower = baseline_policy("slower", layout, n_actions)
        over_slower = run_search(BASELINE_LABELS["slower"], "", slower)
        searched.insert(0, (scripted["slower"], over_slower))
        rows += [(search, None) for _, search in searched]
    lines = [
        f"{env_cfg.scenario}: {args.episodes} highway-env episodes, seeds "
        f"{args.seed}..{args.seed + args.episodes - 1}",
        "",
        "| policy | return | crash rate | tensor simulator, same episodes | transfer gap "
        "(return, crash rate) |",
        "|---|---|---|---|---|",
        *(_row(res, tensor) for res, tensor in rows),
        "",
    ]
    beats = dict.fromkeys((*baselines, "ppo"), 0)
    for grpo, ppo in zip(trained["grpo"], trained["ppo"], strict=True):
        for key, other in (*((b, scripted[b]) for b in baselines), ("ppo", ppo)):
            beats[key] += paired_difference(grpo, other)[2]
            lines.append(f"- {compare_paired(grpo, other)}")
    for greedy, search in searched:
        lines.append(f"- {compare_paired(search, greedy)}")
    n = len(trained["grpo"])
    lines += [
        "",
        "GRPO beats "
        + ", ".join(f"{BASELINE_LABELS[b]} in {beats[b]} of {n} seeds" for b in baselines)
        + f", PPO of the same seed in {beats['ppo']} of {n}.",
        "",
        *(f"- {_training(run)}" for run in [*args.grpo, *args.ppo]),
    ]
    text = "\n".join(lines)
    (out / f"table_{args.seed}_{args.episodes}.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
