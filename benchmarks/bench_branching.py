"""Branch rollout throughput: workers scaling, and the cost of restores and masking.

Measures, in one run and interleaved (so that load from other processes hits every
configuration alike), the valid branch steps per second of

- ``raw``: a plain ``HighwayEnv`` stepped in a loop (reset on done), the policy
  called on every step: the reference rate of one core;
- ``single``: ``branch_rollout`` on that plain env (restores, masking, bookkeeping,
  all in this process);
- ``W=1`` / ``W=2``: ``branch_rollout`` on a ``BranchParallelEnv`` of 1 / 2 workers
  (``HighwayEnv(..., return_state=True)`` workers, as ``make_branch_env`` builds them);
- ``W=2 spin``: the same on TorchRL's own ``ParallelEnv``, whose parent spins on
  the workers' done flags and so keeps a core busy;

and prints the ratios ``W=2 / W=1`` (goal >= 1.7 on 2 cores), ``single / raw`` and
``W=1 / raw`` (what restores, masking and the worker round trips cost). The load
average is printed too: on a shared machine, other processes take cores from the
workers and the ratios with them.

Run: ``python benchmarks/bench_branching.py [--scenario highway-fast-v0] [--repeats 5]``
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing
import os
import statistics
import time
import warnings

import torch
from claims import claim
from torchrl.envs import ParallelEnv

from torchrl_grpo.branching import (
    branch_rollout,
    make_branch_env,
    reset_roots,
    shutdown_env,
)
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor

warnings.filterwarnings("ignore", message=".*is out of date.*")


def _burn(n: int) -> int:
    total = 0
    for i in range(n):
        total += i * i
    return total


def cpu_capacity(n: int = 2_000_000) -> float:
    """Speedup of 2 concurrent pure-CPU processes over 1: what the machine offers now.

    2.0 on an idle 2-core machine; less when other processes hold the cores.
    """
    ctx = multiprocessing.get_context("fork")

    def run(k: int) -> float:
        procs = [ctx.Process(target=_burn, args=(n,)) for _ in range(k)]
        start = time.perf_counter()
        for p in procs:
            p.start()
        for p in procs:
            p.join()
        return time.perf_counter() - start

    return 2 * run(1) / run(2)


def make_policy(env: HighwayEnv) -> torch.nn.Module:
    obs = env.observation_spec["observation"].shape
    n_actions = int(env.action_spec.n)
    return make_discrete_actor(KinematicsMLP(obs[-2], obs[-1], out_features=n_actions), n_actions)


def raw_rate(env: HighwayEnv, policy, steps: int) -> float:
    td = env.reset()
    start = time.perf_counter()
    with torch.no_grad():
        for _ in range(steps):
            td = policy(td.unsqueeze(0))[0]
            out = env.step(td.select("observation", "action"))
            td = env.reset() if out["next", "done"].item() else out["next"].select("observation")
    return steps / (time.perf_counter() - start)


def worker_cpu(env) -> float:
    """CPU seconds used so far by a ParallelEnv's worker processes (Linux /proc)."""
    total = 0.0
    for process in env.__dict__.get("_workers") or []:
        try:
            with open(f"/proc/{process.pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            return float("nan")
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def branch_rate(env, policy, roots, group_size: int, horizon: int, cpu: dict) -> float:
    """Valid branch steps per second; adds parent / worker CPU seconds and steps to ``cpu``."""
    parent, workers = time.process_time(), worker_cpu(env)
    start = time.perf_counter()
    data = branch_rollout(env, policy, roots, group_size, horizon)
    elapsed = time.perf_counter() - start
    steps = int(data["mask"].sum())
    cpu["parent"] += time.process_time() - parent
    cpu["workers"] += worker_cpu(env) - workers
    cpu["steps"] += steps
    return steps / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="highway-fast-v0")
    parser.add_argument("--roots", type=int, default=2, help="R roots per rollout")
    parser.add_argument("--group-size", type=int, default=4, help="G branches per root")
    parser.add_argument("--horizon", type=int, default=10, help="H steps per branch")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds (medians)")
    parser.add_argument(
        "--start-method",
        default="fork",
        choices=["fork", "spawn", "forkserver"],
        help="ParallelEnv start method (startup is not timed)",
    )
    args = parser.parse_args()
    # The policy runs in this process next to the workers: one thread keeps it from
    # competing with them for the 2 cores.
    torch.set_num_threads(1)
    torch.manual_seed(0)

    plain = HighwayEnv(args.scenario, seed=0)
    policy = make_policy(plain)
    roots = reset_roots(HighwayEnv(args.scenario), args.roots, seed=0)
    branch_steps = args.roots * args.group_size * args.horizon
    envs = {
        "single": plain,
        "W=1": make_branch_env(args.scenario, 1, mp_start_method=args.start_method),
        "W=2": make_branch_env(args.scenario, 2, mp_start_method=args.start_method),
        "W=2 spin": ParallelEnv(
            2,
            functools.partial(HighwayEnv, args.scenario, return_state=True),
            mp_start_method=args.start_method,
        ),
    }
    rates: dict[str, list[float]] = {name: [] for name in ("raw", *envs)}
    cpu = {name: {"parent": 0.0, "workers": 0.0, "steps": 0} for name in envs}
    capacity: list[float] = []
    load_before = os.getloadavg()[0]
    try:
        for env in envs.values():  # warm-up: worker start, first restores
            branch_rollout(env, policy, roots, args.group_size, 2)
        raw_env = HighwayEnv(args.scenario, seed=1)
        for _ in range(args.repeats):
            capacity.append(cpu_capacity())
            rates["raw"].append(raw_rate(raw_env, policy, branch_steps))
            for name, env in envs.items():
                rates[name].append(
                    branch_rate(env, policy, roots, args.group_size, args.horizon, cpu[name])
                )
    finally:
        for name, env in envs.items():
            if name != "single":
                shutdown_env(env)

    med = {name: statistics.median(values) for name, values in rates.items()}
    print(
        f"{args.scenario}: R={args.roots} G={args.group_size} H={args.horizon} "
        f"({branch_steps} branch steps per rollout), {args.repeats} rounds, medians; "
        f"{os.cpu_count()} cores, load average {load_before:.1f} -> {os.getloadavg()[0]:.1f}"
    )
    for name, value in med.items():
        spread = f"{min(rates[name]):.1f}-{max(rates[name]):.1f}"
        print(f"  {name:>8}: {value:7.1f} steps/s   (range {spread})")
    print(
        f"  2-process speedup of a pure CPU task, same rounds: {statistics.median(capacity):.2f} "
        f"(range {min(capacity):.2f}-{max(capacity):.2f}; 2.00 on an idle 2-core machine)"
    )
    print("  CPU per branch step (ms): parent / workers")
    per_step = {}
    for name in ("W=1", "W=2", "W=2 spin"):
        c = cpu[name]
        per_step[name] = (1e3 * c["parent"] / c["steps"], 1e3 * c["workers"] / c["steps"])
        print(f"  {name:>8}: {per_step[name][0]:6.2f} / {per_step[name][1]:6.2f}")
    # Lock-step: with W workers, each policy call (parent) is followed by W worker
    # steps in parallel, so a round of W steps takes about W * parent + worker when
    # every process has a core of its own.
    p1, w1 = per_step["W=1"]
    p2, w2 = per_step["W=2"]
    print("ratios")
    claim(
        f"{args.scenario}: branch steps/s, 2 workers / 1 worker", med["W=2"] / med["W=1"], ">=1.7"
    )
    print(f"  W=2 spin / W=1 = {med['W=2 spin'] / med['W=1']:.2f}   (TorchRL's spinning parent)")
    print(
        f"  W=2 / W=1 projected from CPU times on 2 free cores = "
        f"{2 * (p1 + w1) / (2 * p2 + w2):.2f}"
    )
    claim(f"{args.scenario}: branch steps/s, 2 workers / raw single env", med["W=2"] / med["raw"])
    claim(
        f"{args.scenario}: branch steps/s in process / raw env (restores + masking)",
        med["single"] / med["raw"],
    )
    print(f"  W=1 / raw    = {med['W=1'] / med['raw']:.2f}   (+ worker round trips, states)")


if __name__ == "__main__":
    main()
