"""What snapshot lookahead reaches: LookaheadPolicy over a base policy vs the base alone.

Each decision tries every action from the current state, follows the base policy for
the rest of the horizon and keeps the best branch: the exact version of the groups of
``algo.first_action=enumerate algo.tail_policy=<base>``. Evaluation protocol of
``scripts/evaluate.py``: greedy, episodes from seeds 10000, 10001, ...

    python benchmarks/bench_lookahead.py --base rule --horizon 4 --episodes 30
"""

import argparse
import logging
import time

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import KinematicsLayout, make_scripted_policy
from torchrl_grpo.training import evaluate, format_table

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_lookahead")

p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
p.add_argument("--scenario", default="highway-fast-v0")
p.add_argument("--base", default="rule", help="a scripted policy (SCRIPTED_POLICIES)")
p.add_argument("--horizon", type=int, default=4)
p.add_argument("--episodes", type=int, default=30)
p.add_argument("--seed", type=int, default=10_000)
args = p.parse_args()

env = HighwayEnv(args.scenario, return_state=True)
layout = KinematicsLayout.from_highway_config(env.config)
base = make_scripted_policy(args.base, layout)
planner = LookaheadPolicy(HighwayEnv(args.scenario), base, horizon=args.horizon)
results = []
for name, policy in ((args.base, base), (f"lookahead H={args.horizon} over {args.base}", planner)):
    t0 = time.perf_counter()
    res, _ = evaluate(env, policy, episodes=args.episodes, seed=args.seed, name=name)
    results.append(res)
    log.info("%s: %.0f s", name, time.perf_counter() - t0)
log.info("%s", format_table(results))
steps = sum(results[1].lengths)
log.info(
    "planning cost: %d simulated steps per decision (%d decisions)",
    round(planner.frames / max(steps, 1)),
    steps,
)
