"""Branch rollouts against the machine's ceiling: W workers vs W raw highway-env processes.

The ceiling of W workers is W independent processes that each step a raw
highway-env env (``gymnasium.make``, random actions) as fast as they can, in
segments of H steps from episode starts (as branches from reset roots run), timing
the steps only: what the machine gives highway-env alone. Against it, in the same run
and interleaved round by round (so that load from other processes hits both sides
alike), this script times ``branch_rollout`` on a ``BranchParallelEnv`` of W workers
(``make_branch_env``, an MLP actor), with each engine:

- ``whole``: whole branches in the workers, each with its own copy of the policy
  (the default: ``whole_branches = True``, ``branch_queue_depth = 2``);
- ``whole-q1``: the same with one branch at a time per worker
  (``branch_queue_depth = 1``);
- ``lockstep``: the lock-step engine, the policy in this process
  (``whole_branches = False``, as for a policy that cannot be sent to the workers):
  every step, the policy, then all workers step, then the parent waits for the slowest.

The workers' HighwayEnv computes highway-env's Kinematics observation without pandas
(``FastKinematicObservation``: the same bits, about 3 ms less per step), so a worker
steps faster than a raw process. A second ceiling, raw processes given that same
observation, isolates what the branching machinery itself costs; both ratios are
printed.

Each round times the ceilings, then the engines back to back (in an order that turns
round by round), and takes the ratios of that round; the script prints the median
ratio (and range) to the ceiling for every scenario, W and engine, with the load
average. Start-up (forks, env construction, the first restores of each lane) is
not timed.

Run: ``python benchmarks/bench_ceiling.py [--workers 1 2] [--repeats 3]``
(``--workers 1 2 4 8 14`` on a 16-core host). Where the cores go (CPU, run-queue
wait and sleep per step of the parent, the workers and the raw processes):
``bench_ceiling_cpu.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import os
import statistics
import time
import warnings
from collections.abc import Iterator

import torch
from claims import claim

from torchrl_grpo.branching import branch_rollout, make_branch_env, reset_roots, shutdown_env
from torchrl_grpo.branching.workers import BranchParallelEnv
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.envs.highway.fast_observation import use_fast_kinematics
from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor

warnings.filterwarnings("ignore", message=".*is out of date.*")
SCENARIOS = ("highway-fast-v0", "merge-v0")
# Engine -> (whole_branches, branch_queue_depth); the first is the default.
ENGINES = {
    "whole": (True, 2),
    "whole-q1": (True, 1),
    "lockstep": (False, 1),
}


@contextlib.contextmanager
def use_engine(env: BranchParallelEnv, name: str) -> Iterator[None]:
    """Run ``env``'s branch rollouts with engine ``name`` (see ``ENGINES``)."""
    env.whole_branches, env.branch_queue_depth = ENGINES[name]
    try:
        yield
    finally:
        del env.whole_branches, env.branch_queue_depth


def make_raw_env(scenario: str, seed: int):
    """A raw highway-env env (``gymnasium.make``), reset and its action space seeded."""
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers the scenarios)

    warnings.filterwarnings("ignore")
    env = gym.make(scenario)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    return env


def step_segments(
    env, steps: int, horizon: int, clock=time.perf_counter, fast: bool = False
) -> float:
    """Take ``steps`` random steps in segments of ``horizon``; the time stepping took.

    Segments of H steps from episode starts, as branches from reset roots are; only
    the steps are timed by ``clock`` (resets cost more than restores). With ``fast``,
    the Kinematics observation is the workers' (``FastKinematicObservation``).
    """
    stepping = 0.0
    for i in range(steps):
        if i % horizon == 0:
            env.reset()
        if fast:
            use_fast_kinematics(env.unwrapped)  # every reset rebuilds the observation
        start = clock()
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        stepping += clock() - start
        if terminated or truncated:
            env.reset()
    return stepping


def _raw_worker(
    scenario: str, steps: int, horizon: int, seed: int, fast: bool, barrier, out
) -> None:
    env = make_raw_env(scenario, seed)
    barrier.wait()
    out.put(steps / step_segments(env, steps, horizon, fast=fast))


def ceiling_rate(
    scenario: str, workers: int, steps: int, horizon: int, fast: bool = False
) -> float:
    """Steps/s of ``workers`` raw highway-env processes run together (``steps`` each).

    With ``fast``, their Kinematics observation is the workers' (the ceiling of the
    branching machinery alone, without the faster observation's gain).
    """
    ctx = multiprocessing.get_context("fork")
    barrier, out = ctx.Barrier(workers), ctx.Queue()
    args = (scenario, steps, horizon)
    procs = [
        ctx.Process(target=_raw_worker, args=(*args, seed, fast, barrier, out))
        for seed in range(workers)
    ]
    for p in procs:
        p.start()
    total = sum(out.get() for _ in procs)
    for p in procs:
        p.join()
    return total


def branch_rate(env, policy, roots, group_size: int, horizon: int) -> float:
    """Valid branch steps per second of one ``branch_rollout``."""
    start = time.perf_counter()
    data = branch_rollout(env, policy, roots, group_size, horizon)
    return int(data["mask"].sum()) / (time.perf_counter() - start)


def make_policy(env: HighwayEnv) -> torch.nn.Module:
    obs = env.observation_spec["observation"].shape
    n = int(env.action_spec.n)
    return make_discrete_actor(KinematicsMLP(obs[-2], obs[-1], out_features=n), n)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2], help="values of W")
    parser.add_argument("--roots", type=int, default=2, help="R roots per worker")
    parser.add_argument("--group-size", type=int, default=4, help="G branches per root")
    parser.add_argument("--horizon", type=int, default=8, help="H steps per branch")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds")
    parser.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    args = parser.parse_args()
    # The policy runs in this process next to the workers: one thread.
    torch.set_num_threads(1)
    torch.manual_seed(0)
    setups = {}
    for scenario in args.scenarios:
        plain = HighwayEnv(scenario, seed=0)
        for w in args.workers:
            roots = reset_roots(plain, args.roots * w, seed=w)
            env = make_branch_env(scenario, w, mp_start_method="fork")
            # Warms the workers up, for each engine.
            for name in ENGINES:
                with use_engine(env, name):
                    branch_rollout(env, make_policy(plain), roots, args.group_size, 2)
            setups[scenario, w] = (env, make_policy(plain), roots)
    steps_per_branch_run = args.roots * args.group_size * args.horizon
    engines = [e for e in ENGINES if e in args.engines]
    ratios = {k: {e: [] for e in engines} for k in setups}
    # The same rates over raw processes that observe as the workers do (no pandas).
    overhead = {k: {e: [] for e in engines} for k in setups}
    ceilings: dict[tuple, list[float]] = {k: [] for k in setups}
    fast_ceilings: dict[tuple, list[float]] = {k: [] for k in setups}
    load = [os.getloadavg()[0]]
    try:
        for round_ in range(args.repeats):
            for (scenario, w), (env, policy, roots) in setups.items():
                # Raw processes take as many steps each as one worker takes in a rollout.
                ceiling = ceiling_rate(scenario, w, steps_per_branch_run, args.horizon)
                ceilings[scenario, w].append(ceiling)
                fast = ceiling_rate(scenario, w, steps_per_branch_run, args.horizon, fast=True)
                fast_ceilings[scenario, w].append(fast)
                turn = round_ % len(engines)
                for name in engines[turn:] + engines[:turn]:
                    with use_engine(env, name):
                        rate = branch_rate(env, policy, roots, args.group_size, args.horizon)
                    ratios[scenario, w][name].append(rate / ceiling)
                    overhead[scenario, w][name].append(rate / fast)
            load.append(os.getloadavg()[0])
    finally:
        for env, _, _ in setups.values():
            shutdown_env(env)
    print(
        f"R={args.roots}*W G={args.group_size} H={args.horizon}, {args.repeats} interleaved "
        f"rounds, medians (ranges) of branch steps/s over the ceiling; {os.cpu_count()} cores, "
        f"load average {min(load):.1f}-{max(load):.1f} (1-minute, sampled between rounds)"
    )
    for title, table, ceils in (
        ("raw highway-env processes (the ceiling)", ratios, ceilings),
        (
            "raw processes with the workers' observation (the branching overhead alone)",
            overhead,
            fast_ceilings,
        ),
    ):
        print(f"  over {title}:")
        header = f"  {'scenario':<16} {'W':>2} {'ceiling/s':>9}"
        print(header + "".join(f" {e:>16}" for e in engines))
        for (scenario, w), r in table.items():
            cells = [f"{statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f})" for v in r.values()]
            print(
                f"  {scenario:<16} {w:>2} {statistics.median(ceils[scenario, w]):9.1f}"
                + "".join(f" {c:>16}" for c in cells)
            )
    note = f"load {min(load):.1f}-{max(load):.1f} on {os.cpu_count()} cores"
    for (scenario, w), r in overhead.items():
        claim(
            f"{scenario}: branch steps/s on {w} worker(s) / {w} raw processes observing "
            "without pandas",
            statistics.median(r[engines[0]]),
            note=note,
        )
    for (scenario, w), r in ratios.items():
        for name, values in r.items():
            default = name == next(iter(ENGINES))
            claim(
                f"{scenario}: branch steps/s on {w} worker(s) / {w} raw processes"
                if default
                else f"{scenario}, W={w}: the same, {name}",
                statistics.median(values),
                ">=0.85" if default else None,
                note=note,
            )


if __name__ == "__main__":
    main()
