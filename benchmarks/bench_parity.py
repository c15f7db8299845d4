"""The parity ladder at full size: TensorHighwayEnv against highway-env itself (docs/sim.md).

Usage: ``python benchmarks/bench_parity.py [--scenario highway-fast-v0 | highway-v0 |
merge-v0 | roundabout-v0 | intersection-v0] [--worlds 2000] [--episodes 500] [--fresh 1000]
[--native]``

``--native``: the same ladder for the C++ step (``TensorHighwayEnv(native=True)``:
highway-v0, highway-fast-v0, roundabout-v0).

Float64 on CPU, worlds moved through the bridge. Rungs (issue #17):

a. on ``--worlds`` worlds recorded from highway-env runs of the rule, random and
   always-FASTER policies (intersection-v0: always-FASTER, random, always-IDLE; lane
   changes in progress, near misses and crashes among them): the observation, reward
   and flags agree to 1e-9;
b. from each of those worlds, each action (5; intersection-v0's 3): every vehicle's position,
   heading, speed, lane, target lane and crash flag agree after the step to 1e-6 in
   at least 99.5% of (world, action) pairs; every miss is listed with its explanation;
c. whole episodes of the rule policy (intersection-v0: random actions) from ``--episodes``
   imported worlds: at least 95%
   agree to 1e-6 to the end; the distribution of agreement horizons is printed;
d. ``--fresh`` fresh episodes per policy (always-IDLE, always-SLOWER, random, rule;
   intersection-v0: always-FASTER for the rule),
   no bridge, against highway-env's statistics stored by
   ``scripts/highway_reference.py``: no test differs at p < 0.01 after a Bonferroni
   correction over all of them.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import torch
from claims import claim

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.envs.highway.parity import (
    fresh_resets,
    one_step,
    record_worlds,
    same_world,
    whole_episodes,
)
from torchrl_grpo.envs.highway.parity_policies import ladder_policies, recording_policies

REFERENCE = Path(__file__).resolve().parents[1] / "tests" / "data" / "highway_reference"
FRESH_SEED = 1_000_000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="highway-fast-v0")
    parser.add_argument("--worlds", type=int, default=2000)
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--fresh", type=int, default=1000)
    parser.add_argument("--native", action="store_true", help="the C++ step's ladder")
    args = parser.parse_args()
    torch.set_num_threads(1)
    scenario = args.scenario
    native = args.native
    env = TensorHighwayEnv(scenario, num_envs=args.worlds, dtype=torch.float64, native=native)
    policies = ladder_policies(scenario, env.config)
    drive = policies.pop("drive")
    start = time.perf_counter()
    states, kinds = record_worlds(scenario, recording_policies(scenario, env.config), args.worlds)
    took = time.perf_counter() - start
    print(f"{scenario}: {args.worlds} worlds recorded ({kinds}) in {took:.0f} s")

    worst = same_world(env, states)
    rung = f"{scenario} a ({args.worlds} worlds)"
    claim(f"{rung}: max |observation difference|", worst["observation"], "<=1e-9")
    claim(f"{rung}: max |reward component difference|", worst["reward"], "<=1e-9")
    claim(f"{rung}: worlds whose crash / on-road flags differ", worst["flags"], "<=0")

    report = one_step(env, states)
    errors = ", ".join(f"{k} {v:.1e}" for k, v in report.max_error.items())
    note = f"{report.agree} of {report.pairs}; max errors: {errors}"
    claim(f"{scenario} b: (world, action) pairs agreeing to 1e-6", report.agreement, ">=0.995",
          note=note)  # fmt: skip
    for miss in report.misses:
        print(
            f"    miss: world {miss.world} action {miss.action} vehicle {miss.vehicle} "
            f"{miss.field} off by {miss.error:.3g}: {miss.explanation}"
        )

    small = TensorHighwayEnv(scenario, num_envs=args.episodes, dtype=torch.float64, native=native)
    pick = torch.linspace(0, args.worlds - 1, args.episodes).long()
    horizons = whole_episodes(small, states[pick], drive)
    agree = float((horizons == -1).double().mean())
    spread = dict(sorted(Counter(horizons[horizons >= 0].tolist()).items()))
    note = f"{args.episodes} episodes; diverged at step: {spread}"
    claim(f"{scenario} c: episodes agreeing to 1e-6 to the end", agree, ">=0.95", note=note)

    path = REFERENCE / f"{scenario}.json"
    if not path.exists():
        print(f"  d skipped: no {path} (run scripts/highway_reference.py --scenario {scenario})")
        return
    reference = json.loads(path.read_text())
    # merge-v0's, roundabout-v0's and intersection-v0's fresh worlds replay highway-env's
    # own generator:
    # seeds disjoint from the reference's (0 .. episodes - 1), or both sides would draw
    # the very same episodes.
    seed = FRESH_SEED if env._model.draws_from_words else 0
    table = fresh_resets(
        scenario, reference, policies, episodes=args.fresh, seed=seed, native=native
    )
    n = len(table)
    threshold = 0.01 / n
    for row in table:
        print(
            f"    {row['what']:<22} tensor {row['tensor']:9.4f}  highway-env "
            f"{row['highway']:9.4f}  statistic {row['statistic']:7.4f}  p {row['p']:.3g}"
        )
    what = f"{scenario} d: smallest p of {n} fresh-reset tests (Bonferroni 0.01/{n})"
    note = f"{args.fresh} tensor episodes per policy, {reference['episodes']} highway-env"
    claim(what, min(r["p"] for r in table), f">={threshold:.6f}", note=note)


if __name__ == "__main__":
    main()
