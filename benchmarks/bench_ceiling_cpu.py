"""Where the cores go in branch rollouts: CPU seconds per step of every process.

Runs ``branch_rollout`` on a ``BranchParallelEnv`` of W workers (the default engine:
whole branches in the workers; ``--engine`` picks another, see ``bench_ceiling.py``)
and, interleaved with it, W raw highway-env processes (the ceiling of
``bench_ceiling.py``), and reads each process's CPU time (``utime + stime`` of
``/proc/<pid>/stat``) and context switches (``/proc/<pid>/status``) before and
after, beside the wall time. CPU seconds per step do not depend on how loaded the
machine is (wall times do): they say whether branch rollouts lose to the ceiling by
doing more work (worker CPU per branch step above raw CPU per step, or the parent's
CPU) or by waiting (idle = W * wall - CPU of all processes, when W cores are free).

Prints, per scenario: ms of CPU per step of the parent, of the workers (per branch
step) and of the raw processes (per raw step, resets of the segments included),
wall ms per step, idle share, and context switches per step; for the workers, the
part of their sleep spent at the end of rollouts (from a worker's last answer of a
rollout to the rollout's end, summed over workers).

Run: ``python benchmarks/bench_ceiling_cpu.py [--workers 2] [--rollouts 4]``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
import warnings

import torch
from bench_ceiling import ENGINES, make_policy, make_raw_env, step_segments, use_engine

from torchrl_grpo.branching import (
    branch_rollout,
    make_branch_env,
    reset_roots,
    shutdown_env,
)
from torchrl_grpo.envs import HighwayEnv

warnings.filterwarnings("ignore", message=".*is out of date.*")
TICK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int | str = "self") -> float:
    """utime + stime of process ``pid`` (all its threads), in seconds."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def switches(pid: int | str = "self") -> tuple[int, int]:
    """(voluntary, involuntary) context switches of process ``pid``."""
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if "ctxt_switches" in line:
                name, value = line.split(":")
                out[name.strip()] = int(value)
    return out["voluntary_ctxt_switches"], out["nonvoluntary_ctxt_switches"]


def run_delay(pid: int | str = "self") -> float:
    """Seconds the main thread of ``pid`` waited, runnable, for a core (``schedstat``)."""
    with open(f"/proc/{pid}/schedstat") as f:
        return int(f.read().split()[1]) / 1e9


def sample(pids: list) -> list[tuple[float, int, int, float]]:
    """(CPU s, voluntary switches, involuntary switches, run-queue wait s) per process."""
    return [(cpu_seconds(p), *switches(p), run_delay(p)) for p in pids]


def account(before: list, after: list, wall: float, steps: int) -> dict[str, float]:
    """Per-step means over processes: CPU, run-queue wait and sleep (ms), switches.

    ``steps`` is the number of steps the processes took together; sleep is the wall
    time a process spent neither running nor waiting for a core: waiting for work.
    """
    d = [[a - b for a, b in zip(x, y, strict=True)] for x, y in zip(after, before, strict=True)]
    cpu, wait = sum(x[0] for x in d), sum(x[3] for x in d)
    return {
        "cpu": 1e3 * cpu / steps,
        "wait": 1e3 * wait / steps,
        "sleep": 1e3 * (len(d) * wall - cpu - wait) / steps,
        "vcs": sum(x[1] for x in d) / steps,
        "ics": sum(x[2] for x in d) / steps,
    }


def _raw_worker(scenario: str, steps: int, horizon: int, seed: int, go, done, out) -> None:
    env = make_raw_env(scenario, seed)
    go.wait()
    out.put(step_segments(env, steps, horizon, clock=time.process_time))
    done.wait()


def raw_run(scenario: str, workers: int, steps: int, horizon: int) -> dict:
    """Accounting of ``workers`` raw processes taking ``steps`` steps each."""
    ctx = multiprocessing.get_context("fork")
    go, done, out = ctx.Barrier(workers + 1), ctx.Barrier(workers + 1), ctx.Queue()
    procs = [
        ctx.Process(target=_raw_worker, args=(scenario, steps, horizon, s, go, done, out))
        for s in range(workers)
    ]
    for p in procs:
        p.start()
    pids = [p.pid for p in procs]
    go.wait()
    before, start = sample(pids), time.perf_counter()
    step_cpu = sum(out.get() for _ in procs)
    wall = time.perf_counter() - start
    after = sample(pids)
    done.wait()
    for p in procs:
        p.join()
    n = steps * workers
    acc = account(before, after, wall, n)
    acc["wall"] = 1e3 * wall * workers / n
    acc["step_cpu"] = 1e3 * step_cpu / n
    return {"raw": acc}


def branch_run(env, policy, roots, group_size: int, horizon: int, rollouts: int) -> dict:
    """Accounting of the parent and the workers over ``rollouts`` branch rollouts."""
    workers = [p.pid for p in env._workers]
    # When each worker's last answer of a rollout came: a worker idles from then on
    # until the rollout ends (the end-of-rollout idle).
    answered: dict[int, float] = {}
    read = env.branch_answer

    def logged(worker: int):
        out = read(worker)
        answered[worker] = time.perf_counter()
        return out

    env.branch_answer = logged
    idle = 0.0
    before, start = sample(["self", *workers]), time.perf_counter()
    steps = 0
    try:
        for _ in range(rollouts):
            answered.clear()
            data = branch_rollout(env, policy, roots, group_size, horizon)
            end = time.perf_counter()
            steps += int(data["mask"].sum())
            idle += sum(end - answered.get(w, end) for w in range(len(workers)))
    finally:
        del env.branch_answer
    wall = time.perf_counter() - start
    after = sample(["self", *workers])
    worker = account(before[1:], after[1:], wall, steps)
    worker["wall"] = 1e3 * wall * len(workers) / steps
    worker["tail"] = 1e3 * idle / steps
    return {"parent": account(before[:1], after[:1], wall, steps), "workers": worker}


def row(scenario: str, name: str, acc: dict) -> str:
    return (
        f"  {scenario:<16} {name:<8} {acc.get('wall', float('nan')):6.1f} {acc['cpu']:6.2f} "
        f"{acc['wait']:6.2f} {acc['sleep']:6.2f} {acc['vcs']:6.2f} {acc['ics']:6.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=["highway-fast-v0", "merge-v0"])
    parser.add_argument("--workers", type=int, default=2, help="W")
    parser.add_argument("--engine", default=next(iter(ENGINES)), choices=ENGINES)
    parser.add_argument("--roots", type=int, default=2, help="R roots per worker")
    parser.add_argument("--group-size", type=int, default=4)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--rollouts", type=int, default=3, help="rollouts per measurement")
    parser.add_argument("--repeats", type=int, default=2, help="interleaved rounds")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    w = args.workers
    print(
        f"W={w} engine={args.engine} R={args.roots}*W G={args.group_size} H={args.horizon}; "
        f"ms per step (per branch step of all workers / raw step of all raw processes); "
        f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    print(
        f"  {'scenario':<16} {'process':<8} {'wall':>6} {'cpu':>6} {'runq':>6} {'sleep':>6} "
        f"{'vcs':>6} {'ics':>6}"
    )
    for scenario in args.scenarios:
        plain = HighwayEnv(scenario, seed=0)
        roots = reset_roots(plain, args.roots * w, seed=w)
        env = make_branch_env(scenario, w, mp_start_method="fork")
        policy = make_policy(plain)
        steps = args.roots * args.group_size * args.horizon * args.rollouts
        try:
            with use_engine(env, args.engine):
                branch_rollout(env, policy, roots, args.group_size, 2)
            for _ in range(args.repeats):
                raw = raw_run(scenario, w, steps, args.horizon)
                with use_engine(env, args.engine):
                    branch = branch_run(
                        env, policy, roots, args.group_size, args.horizon, args.rollouts
                    )
                print(
                    row(scenario, "raw", raw["raw"])
                    + f"  (steps only {raw['raw']['step_cpu']:.2f})"
                )
                print(
                    row(scenario, "workers", branch["workers"])
                    + f"  (end-of-rollout idle {branch['workers']['tail']:.2f})"
                )
                print(row(scenario, "parent", branch["parent"]))
        finally:
            shutdown_env(env)


if __name__ == "__main__":
    main()
