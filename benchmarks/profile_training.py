"""Where the main job's time goes: simulator, policy inference, learner, the rest (issue #41).

Usage: ``python benchmarks/profile_training.py [--iterations 5] [--warmup N] [--threads N]
[--torch-profile] [override ...]``

Runs the main job's recipe (``scripts/train.py``'s config, composed with the same Hydra
config and the overrides given; GRPO with snapshot branching on highway-fast-v0, the
tensor simulator) through :class:`~torchrl_grpo.training.Trainer` for ``--warmup`` then
``--iterations`` training iterations, with no evaluation, checkpoint, plot or logger,
and prints for each measured iteration, side by side, its seconds (wall, or with
``--clock cpu`` CPU) and the seconds and share of:

* ``sim``: the simulator (``TensorHighwayEnv.step``, ``reset``, ``get_state``: branch
  rollouts, trunk segments, restores, new episodes);
* ``policy``: the policy's calls during collection (the learner, the greedy tail's
  scripted policy, on trunks and branches);
* ``collect-other``: the rest of collection (tensordict bookkeeping of the rollouts,
  action checks, root sources);
* ``prep``: the learner's batch preparation (bootstrap, advantages, crash labels, replay,
  the current policy's log-probs);
* ``update``: the learner's minibatch passes (loss forward, backward, optimiser);
* ``other``: everything else of the iteration (metrics, EMA, learning-rate anneal,
  the trainer's loop).

Times are exclusive (a phase's time excludes the phases timed inside it); the timers
are ``time.perf_counter`` wrappers installed from here, none in the library. Then the
end-to-end frames/s of the measured iterations, the simulator's own rate in the same
process (the same ``TensorHighwayEnv`` config at the same batch, always-IDLE through
``step_and_maybe_reset``, as ``benchmarks/bench_tensor_env.py``; a block of 8 steps after
each measured iteration, not counted in it; the median), and their ratio.

The warm-up runs until the replay (``algo.replay_groups``) is full: the learner's update
grows with it until then (17 iterations for the recipe), and stays at that cost after.

The issue #41 item 4 figures (docs/benchmarks.md, "Training keeps up"), on one core::

    OMP_NUM_THREADS=1 taskset -c 1 python benchmarks/profile_training.py --threads 1

Another checkout's library, the same profile (e.g. before a change)::

    OMP_NUM_THREADS=1 PYTHONPATH=/work/main taskset -c 1 python benchmarks/profile_training.py \
        --threads 1

``--torch-profile`` also prints ``torch.profiler``'s table of the measured iterations'
operators (self CPU time), to see what dominates inside a phase.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import statistics
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from typing import Any

import torch
from bench_tensor_env import tensor_stepper

import torchrl_grpo.branching.dispatch as dispatch
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.training import Hook, Trainer, compose_config
from torchrl_grpo.training.collect import world_steps

#: What the timers read: wall seconds, or with ``--clock cpu`` this thread's CPU seconds
#: (with one torch thread, everything the run computes; a share of a busy core then
#: counts as what it costs, not as the time it waited for the core).
clock = time.perf_counter

PHASES = ("sim", "policy", "collect-other", "prep", "update", "other")
#: What the profile switches off: evaluation, checkpoints, plots, logging.
QUIET = [
    "logger=none",
    "experiment.eval_every=0",
    "experiment.final_eval_episodes=0",
    "experiment.checkpoint_every=0",
    "experiment.baselines=[]",
]


class ExclusiveTimer:
    """Seconds per phase, each phase's own: time spent in a phase timed inside it is not its."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = defaultdict(float)
        self._stack: list[list[float]] = []  # [start, seconds of the phases inside]

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as ``name``."""
        frame = [clock(), 0.0]
        self._stack.append(frame)
        try:
            yield
        finally:
            self._stack.pop()
            elapsed = clock() - frame[0]
            self.totals[name] += elapsed - frame[1]
            if self._stack:
                self._stack[-1][1] += elapsed

    def wrap(self, name: str, fn: Callable) -> Callable:
        """``fn`` timed as ``name``."""

        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            with self.phase(name):
                return fn(*args, **kwargs)

        return timed

    def pop(self) -> dict[str, float]:
        """The totals so far, then zeros."""
        out = dict(self.totals)
        self.totals.clear()
        return out


def install(timer: ExclusiveTimer) -> None:
    """Wrap the simulator's methods and the branch engine's policy calls (process-wide)."""
    for method in ("step", "reset", "get_state", "step_and_maybe_reset"):
        setattr(TensorHighwayEnv, method, timer.wrap("sim", getattr(TensorHighwayEnv, method)))
    engine = dispatch.run_batched_branches

    @functools.wraps(engine)
    def run_batched_branches(env, policy, *args, **kwargs):
        return engine(env, timer.wrap("policy", policy), *args, **kwargs)

    # Every trunk segment and branch rollout on the tensor simulator goes through here.
    dispatch.run_batched_branches = run_batched_branches


def time_learner(timer: ExclusiveTimer, algo: Any) -> None:
    """Time the algorithm's update (``optimise`` inside it) and its collector's own work."""
    algo.update = timer.wrap("prep", algo.update)
    algo.optimise = timer.wrap("update", algo.optimise)
    make_collector = algo.make_collector

    def timed_collector(seed: int) -> Any:
        collector = make_collector(seed)
        collector._collect = timer.wrap("collect-other", collector._collect)
        return collector

    algo.make_collector = timed_collector


class Recorder(Hook):
    """Each iteration's wall seconds, frames and phase times; stops the run when done."""

    def __init__(
        self,
        timer: ExclusiveTimer,
        warmup: int,
        iterations: int,
        profiler: Any = None,
        sim_block: Callable[[], float] | None = None,
    ) -> None:
        self.timer = timer
        self.warmup = warmup
        self.iterations = iterations
        self.profiler = profiler  # entered once the warm-up is done
        # The simulator alone, measured after every measured iteration (not counted in
        # it), so that both rates see the same machine load.
        self.sim_block = sim_block
        self.sim_rates: list[float] = []
        self.rows: list[dict[str, float]] = []
        self._last: tuple[float, int] = (0.0, 0)
        self._worlds = 0

    def due(self, trainer: Any, batch: Any) -> bool:  # noqa: D102
        return True

    def on_iteration(self, trainer: Any, batch: Any, result: Any) -> dict[str, float]:  # noqa: D102
        now = clock()
        phases = self.timer.pop()
        if trainer.iteration > self.warmup:  # the warm-up includes building the collector
            wall, frames = now - self._last[0], trainer.frames - self._last[1]
            row = {k: phases.get(k, 0.0) for k in PHASES[:-1]}
            row["other"] = wall - sum(row.values())
            worlds = world_steps(trainer.collector) or 0
            row.update(wall=wall, frames=frames, worlds=worlds - self._worlds)
            self.rows.append(row)
        if len(self.rows) >= self.iterations:
            trainer.stop_requested = True
            if self.profiler is not None:
                self.profiler.__exit__(None, None, None)
        elif trainer.iteration == self.warmup and self.profiler is not None:
            self.profiler.__enter__()
        if trainer.iteration > self.warmup and self.sim_block is not None:
            self.sim_rates.append(self.sim_block())
            self.timer.pop()
        self._worlds = world_steps(trainer.collector) or 0
        self._last = (clock(), trainer.frames)
        return {}


def sim_stepper(cfg: Any, calls: int = 8) -> Callable[[], float]:
    """The simulator's own steps/s over ``calls`` steps: ``cfg.env`` at its batch, always
    IDLE, worlds reset as their episodes end (``benchmarks/bench_tensor_env.py``)."""
    batch = int(cfg.env.num_envs)
    native = cfg.env.backend == "native"  # the simulator as the run steps it
    step = tensor_stepper(batch, False, str(cfg.device), cfg.env.scenario, native=native)

    def rate() -> float:
        start = clock()
        for _ in range(calls):
            step()
        return calls * batch / (clock() - start)

    return rate


def default_warmup(cfg: Any) -> int:
    """Iterations until the replay (``algo.replay_groups``) is full, plus one; else one.

    The learner's update grows with the replay until it is full: the recipe's 4,096
    groups fill after 16 batches of 256 groups, and the run then stays at that cost.
    """
    groups = cfg.algo.get("replay_groups")
    per_batch = cfg.rollout.get("groups_per_batch")
    if groups is None or per_batch is None:
        return 1
    return -(-int(groups) // int(per_batch)) + 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=5, help="measured iterations")
    parser.add_argument(
        "--warmup",
        type=int,
        default=None,
        help="iterations before measuring (default: until the replay is full, plus one)",
    )
    parser.add_argument(
        "--threads", type=int, default=len(os.sched_getaffinity(0)), help="torch threads"
    )
    parser.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall seconds, or this thread's CPU seconds (steadier on a shared core)",
    )
    parser.add_argument("--torch-profile", action="store_true", help="torch.profiler's table")
    parser.add_argument("overrides", nargs="*", help="config overrides, as for scripts/train.py")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.clock == "cpu":
        global clock
        clock = time.thread_time
    cfg = compose_config([*QUIET, *args.overrides])
    if args.warmup is None:
        args.warmup = default_warmup(cfg)
    if args.iterations < 1 or args.warmup < 1:
        raise SystemExit("--iterations and --warmup must be >= 1")

    timer = ExclusiveTimer()
    install(timer)
    profiler = None
    if args.torch_profile:
        profiler = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
    recorder = Recorder(timer, args.warmup, args.iterations, profiler, sim_stepper(cfg))
    with tempfile.TemporaryDirectory() as run_dir:
        trainer = Trainer(cfg, run_dir=run_dir)
        trainer.hooks = [recorder]  # no evaluation, plot or checkpoint
        time_learner(timer, trainer.algo)
        trainer.train()

    rows = recorder.rows
    print(
        f"\n{cfg.algo.name} on {cfg.env.scenario}, {cfg.env.num_envs} worlds, "
        f"{args.threads} thread(s), {len(rows)} iterations after {args.warmup} warm-up, "
        f"{args.clock} seconds"
    )
    header = f"| iteration | frames | {args.clock} s | " + " | ".join(PHASES) + " |"
    print(header)
    print("|" + "---|" * (3 + len(PHASES)))
    for i, row in enumerate(rows, 1):
        cells = " | ".join(f"{row[p]:.2f} s {100 * row[p] / row['wall']:.0f}%" for p in PHASES)
        print(f"| {i} | {int(row['frames'])} | {row['wall']:.2f} | {cells} |")
    wall = sum(r["wall"] for r in rows)
    frames = sum(r["frames"] for r in rows)
    cells = " | ".join(
        f"{sum(r[p] for r in rows) / len(rows):.2f} s {100 * sum(r[p] for r in rows) / wall:.0f}%"
        for p in PHASES
    )
    print(f"| mean | {frames / len(rows):.0f} | {wall / len(rows):.2f} | {cells} |")
    fps, sims = frames / wall, recorder.sim_rates
    sim = statistics.median(sims)
    print(
        f"\nend to end: {fps:,.0f} frames/s; simulator alone: {sim:,.0f} steps/s (median of "
        f"{len(sims)} blocks, {min(sims):,.0f} to {max(sims):,.0f}); ratio {fps / sim:.2f}"
    )
    worlds, sim_s = sum(r["worlds"] for r in rows), sum(r["sim"] for r in rows)
    if worlds:
        # Rows stepped and not counted as frames: branches past their end, trunk padding.
        print(
            f"the simulator stepped {worlds / len(rows):,.0f} rows per iteration for "
            f"{frames / len(rows):,.0f} frames ({frames / worlds:.2f}); with nothing but the "
            f"simulator the run would make {frames / sim_s:,.0f} frames/s, ratio "
            f"{frames / sim_s / sim:.2f}"
        )
    if args.torch_profile:
        table = profiler.key_averages().table(sort_by="self_cpu_time_total", row_limit=30)
        print(table)


if __name__ == "__main__":
    main()
