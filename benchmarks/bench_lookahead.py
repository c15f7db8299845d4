"""What snapshot lookahead reaches: LookaheadPolicy over a base policy vs the base alone.

Each decision tries every action from the current state, follows the base policy for
the rest of the horizon and keeps the best branch: the exact version of the groups of
``algo.first_action=enumerate algo.tail_policy=<base>``. Evaluation protocol of
``scripts/evaluate.py``: greedy, episodes from seeds 10000, 10001, ... The base is a
scripted policy, or with ``--checkpoint`` a trained policy's greedy actions. The same
planner also runs with its branches on the tensor simulator, from the highway-env
states imported through the bridge (``search_policy``, what ``scripts/evaluate.py
search_horizon=H`` drives), and its time and returns are printed beside.

    python benchmarks/bench_lookahead.py --base rule --horizon 4 --episodes 30
    python benchmarks/bench_lookahead.py --checkpoint runs/x/last.pt --horizon 8 --episodes 5
"""

import argparse
import logging
import time

from bench_crash_rates import trained
from claims import claim
from omegaconf import OmegaConf

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.modules import KinematicsLayout, make_scripted_policy
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import evaluate, make_env, search_policy
from torchrl_grpo.training.env_builder import tensor_covers
from torchrl_grpo.training.results import format_table

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_lookahead")

p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
p.add_argument("--scenario", default="highway-fast-v0")
p.add_argument("--base", default="rule", help="a scripted policy (SCRIPTED_POLICIES)")
p.add_argument("--checkpoint", default=None, help="a run's last.pt: its greedy policy is the base")
p.add_argument("--horizon", type=int, default=4)
p.add_argument("--episodes", type=int, default=30)
p.add_argument("--seed", type=int, default=10_000)
args = p.parse_args()

env_cfg = OmegaConf.create({"scenario": args.scenario, "config": {}})
if args.checkpoint:
    env_cfg, base = trained(args.checkpoint)
    base, label = DeterministicActor(base), args.checkpoint
else:
    layout = KinematicsLayout.from_highway_config(make_env(env_cfg).config)
    base, label = make_scripted_policy(args.base, layout), args.base
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
log.info("%s", format_table(results))
steps = sum(results[1].lengths)
log.info(
    "planning cost: %d simulated steps per decision (%d decisions)",
    round(planner.frames / max(steps, 1)),
    steps,
)
if len(results) == 3:
    gap = max(abs(a - b) for a, b in zip(results[1].returns, results[2].returns, strict=True))
    note = f"H={args.horizon}, {args.episodes} episodes, {seconds[2] / args.episodes:.1f} s each"
    claim(
        "lookahead on highway-env snapshots / on the tensor simulator, time",
        seconds[1] / seconds[2],
        note=note,
    )
    claim("lookahead: max |episode return difference|, tensor vs highway-env", gap, "<=1e-4")
