"""What snapshot lookahead reaches: LookaheadPolicy over a base policy vs the base alone.

Each decision tries every action from the current state, follows the base policy for
the rest of the horizon and keeps the best branch: the exact version of the groups of
``algo.first_action=enumerate algo.tail_policy=<base>``. Evaluation protocol of
``scripts/evaluate.py``: greedy, episodes from seeds 10000, 10001, ... The base is a
scripted policy, or with ``--checkpoint`` a trained policy's greedy actions. The same
planner also runs with its branches on the tensor simulator, from the highway-env
states imported through the bridge (``search_policy``, what ``scripts/evaluate.py
search_horizon=H`` drove until it played all episodes at once), and the batched planner
that it drives now (``evaluate_search``: all episodes in lock-step, their states imported
in one batch per step, one planning rollout per step); their times and returns are
printed beside.

With ``--on tensor`` (the episodes are worlds of the tensor simulator) or ``--batched``
(highway-env episodes), one run measures side by side today's planner (one 5-row rollout
per decision, a handful of episodes: ``--old-episodes``) and the batched one
(``--episodes``, all at once), both on ``--workers`` processes of one thread (today's
planner on the tensor simulator runs in one, its time divided by ``--workers``):
episodes/s, the time for 1,000 episodes (projected, or measured with ``--episodes
1000``) and the returns of the episodes both played, which must be equal.

    python benchmarks/bench_lookahead.py --base rule --horizon 4 --episodes 30
    python benchmarks/bench_lookahead.py --checkpoint runs/x/last.pt --horizon 8 --episodes 5
    python benchmarks/bench_lookahead.py --on tensor --horizon 8 --episodes 200 --old-episodes 4
    python benchmarks/bench_lookahead.py --batched --horizon 8 --episodes 40 --old-episodes 4
"""

import argparse
import logging
import os
import time

import torch
from bench_crash_rates import trained
from claims import claim
from omegaconf import OmegaConf

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import KinematicsLayout, make_scripted_policy
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import evaluate, make_env, search_policy
from torchrl_grpo.training.env_builder import env_overrides, tensor_covers
from torchrl_grpo.training.results import format_table
from torchrl_grpo.training.search_eval import evaluate_search
from torchrl_grpo.training.transfer import evaluate_on_tensor

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_lookahead")

p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
p.add_argument("--scenario", default="highway-fast-v0")
p.add_argument("--base", default="rule", help="a scripted policy (SCRIPTED_POLICIES)")
p.add_argument("--checkpoint", default=None, help="a run's last.pt: its greedy policy is the base")
p.add_argument("--horizon", type=int, default=4)
p.add_argument("--episodes", type=int, default=30)
p.add_argument("--seed", type=int, default=10_000)
p.add_argument("--on", choices=["highway", "tensor"], default="highway", help="where episodes run")
p.add_argument("--batched", action="store_true", help="only today's planner vs the batched one")
p.add_argument("--old-episodes", type=int, default=4, help="side by side: today's planner's")
p.add_argument("--workers", type=int, default=2, help="side by side: forked processes")
args = p.parse_args()

env_cfg = OmegaConf.create({"scenario": args.scenario, "config": {}, "max_episode_steps": 40})
if args.checkpoint:
    env_cfg, base = trained(args.checkpoint)
    base, label = DeterministicActor(base), args.checkpoint
else:
    layout = KinematicsLayout.from_highway_config(make_env(env_cfg).config)
    base, label = make_scripted_policy(args.base, layout), args.base


def side_by_side(on: str) -> None:
    """Today's planner and the batched one, episodes on ``on``, in one run."""
    if not tensor_covers(env_cfg):
        raise SystemExit(f"--on {on}: the tensor simulator does not cover {args.scenario}")
    log.info("load before: %s", os.getloadavg())
    n_old, n_new, w = args.old_episodes, args.episodes, args.workers
    t0 = time.perf_counter()
    if on == "tensor":
        # Today's search on the tensor simulator (evaluate_on_tensor, as
        # bench_crash_rates.py runs it) with a planning env of 5 rows: the episodes are
        # rows, each row's decision one rollout of its 5 branches. One process of one
        # thread; 1,000 episodes are projected on `w` such processes.
        plan = TensorHighwayEnv(args.scenario, env_overrides(env_cfg), num_envs=5, seed=0)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        res_old = evaluate_on_tensor(
            env_cfg, LookaheadPolicy(plan, base, args.horizon), episodes=n_old, seed=args.seed,
            name="today's planner", return_state=True,
        )  # fmt: skip
        torch.set_num_threads(threads)
        t_old = time.perf_counter() - t0
        log.info("today's planner: %d episodes in %.1f s in one process", n_old, t_old)
        t_old /= w
    else:
        old = search_policy(env_cfg, base, args.horizon)
        driven = make_env(env_cfg, return_state=True)
        res_old, _ = evaluate(
            driven, old, episodes=n_old, seed=args.seed, workers=w, name="today's planner"
        )
        t_old = time.perf_counter() - t0
    t0 = time.perf_counter()
    res_new = evaluate_search(
        env_cfg, base, args.horizon, episodes=n_new, seed=args.seed, on=on, workers=w,
        name="batched planner",
    )  # fmt: skip
    t_new = time.perf_counter() - t0
    log.info("load after: %s", os.getloadavg())
    log.info("%s", format_table([res_old, res_new]))
    both = min(n_old, n_new)
    gap = max(abs(a - b) for a, b in zip(res_old.returns, res_new.returns[:both], strict=False))
    same = (res_old.lengths, res_old.crashed) == (
        res_new.lengths[:both],
        res_new.crashed[:both],
    )
    log.info(
        "%s episodes, H=%d over %s, %d workers of one thread: today's planner %d episodes in "
        "%.1f s on them (%.3f episodes/s, 1,000 episodes: %.0f s projected); batched %d "
        "episodes in %.1f s (%.2f episodes/s, 1,000 episodes: %.0f s %s); equal on the %d "
        "episodes both played: max |return difference| %.2g, lengths and crashes %s",
        on, args.horizon, label, w, n_old, t_old, n_old / t_old, 1000 * t_old / n_old, n_new,
        t_new, n_new / t_new, 1000 * t_new / n_new,
        "measured" if n_new == 1000 else "projected", both, gap,
        "equal" if same else "DIFFERENT",
    )  # fmt: skip
    note = f"H={args.horizon}, {n_new} vs {n_old} episodes, {w} workers"
    claim(f"{on} episodes: batched / today's planner, episodes/s",
          (n_new / t_new) / (n_old / t_old), note=note)  # fmt: skip
    claim(f"{on} episodes: batched planner, seconds for 1,000 episodes",
          1000 * t_new / n_new, "<=120" if on == "tensor" else None, note=note)  # fmt: skip
    claim(f"{on} episodes: batched vs today's planner, max |return difference|", gap, "<=1e-5")


if args.on == "tensor" or args.batched:
    side_by_side(args.on)
    raise SystemExit(0)
env = make_env(env_cfg, return_state=True)
planner = LookaheadPolicy(make_env(env_cfg), base, args.horizon)
policies = [(label, base), (f"lookahead H={args.horizon} over {label}", planner)]
if tensor_covers(env_cfg):
    on_tensor = search_policy(env_cfg, base, args.horizon)
    policies.append(("the same, branching on the tensor simulator", on_tensor))
results, seconds = [], []
for name, policy in policies:
    t0 = time.perf_counter()
    res, _ = evaluate(env, policy, episodes=args.episodes, seed=args.seed, name=name)
    results.append(res)
    seconds.append(time.perf_counter() - t0)
    log.info("%s: %.0f s", name, seconds[-1])
if tensor_covers(env_cfg):
    name = "the same, all episodes at once (lock-step, one import per step)"
    t0 = time.perf_counter()
    res = evaluate_search(
        env_cfg, base, args.horizon, episodes=args.episodes, seed=args.seed, name=name
    )
    results.append(res)
    seconds.append(time.perf_counter() - t0)
    log.info("%s: %.0f s", name, seconds[-1])
log.info("%s", format_table(results))
steps = sum(results[1].lengths)
log.info(
    "planning cost: %d simulated steps per decision (%d decisions)",
    round(planner.frames / max(steps, 1)),
    steps,
)
if len(results) == 4:
    gap = max(abs(a - b) for a, b in zip(results[1].returns, results[2].returns, strict=True))
    note = f"H={args.horizon}, {args.episodes} episodes, {seconds[2] / args.episodes:.1f} s each"
    claim(
        "lookahead on highway-env snapshots / on the tensor simulator, time",
        seconds[1] / seconds[2],
        note=note,
    )
    claim("lookahead: max |episode return difference|, tensor vs highway-env", gap, "<=1e-4")
    batched = max(abs(a - b) for a, b in zip(results[2].returns, results[3].returns, strict=True))
    claim("lookahead on highway-env: batched / one state at a time, time", seconds[2] / seconds[3],
          note=f"H={args.horizon}, {args.episodes} episodes")  # fmt: skip
    claim("lookahead on highway-env: max |return difference|, batched vs one state", batched,
          "<=1e-5")  # fmt: skip
