"""Everything a GPU session measures, in one run of under 8 minutes on one H200.

    python benchmarks/bench_gpu.py                     # cuda, B = 65,536 .. 1,048,576
    python benchmarks/bench_gpu.py --device cpu --sizes 64 --train-frames 256 \\
        --planner-worlds 2 --budget 120                # the CPU smoke run (tests/test_bench_gpu.py)

Each part is skipped (and says so) once ``--budget`` seconds are spent, so that the run
ends in time; the cheap parts run first (eager rates, planner, training), the
compilations last. The parts:

1. env-steps/s of highway-fast-v0, float32, always-IDLE, finished worlds reset, at each B:
   * ``eager``: ``TensorHighwayEnv.step_and_maybe_reset`` (what training calls; on a
     GPU the step takes its dense, sync-free path);
   * ``compiled``: the same env after ``env.compile(dense=True, dynamic=True)`` (the
     whole dense step through Inductor, TorchRL's plumbing eager; GPU only);
   * ``graph``: the pure dense step plus the sync-free reset of finished rows
     (:func:`~torchrl_grpo.sim.reset.reset_world`), through
     ``torch.compile(mode="reduce-overhead", dynamic=True)``: Inductor's kernels
     replayed as CUDA graphs (GPU only), the simulator without TorchRL's per-step Python.
   Every B of one kind runs before the next kind; a size that runs out of memory is
   reported as such.
2. The branch-as-rows lookahead planner
   (:class:`~torchrl_grpo.branching.LookaheadPolicy` on a TensorHighwayEnv, every
   action's branch a row of one batched rollout): ``--planner-worlds`` episodes of at
   most 30 steps driven at once, horizon ``--horizon``, base policy ``slower``:
   episodes/s and planned env-steps/s.
3. The recipe (``scripts/train.py``'s default config, GRPO with branching, on the
   tensor simulator, on ``--device``) for ``--train-frames`` frames, no evaluation:
   training frames/s end to end (collection, policy and learner).

It prints one ``NAME: VALUE`` line per figure and, with ``--json``, writes them all.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from collections.abc import Callable

import torch

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.sim.reset import reset_world
from torchrl_grpo.sim.simulate import step as sim_step

IDLE = 1
GPU_SIZES = [65_536, 131_072, 262_144, 524_288, 1_048_576]
COMPILE_SECONDS = 150  # the room a compilation of the dense step is given
log = logging.getLogger("bench_gpu")


class Clock:
    """The run's time budget."""

    def __init__(self, budget: float) -> None:
        self.start = time.perf_counter()
        self.budget = budget

    def left(self) -> float:
        return self.budget - (time.perf_counter() - self.start)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed_rate(
    fn: Callable[[], None], per_call: int, device: torch.device, seconds: float
) -> float:
    """Env-steps/s of ``fn`` (``per_call`` env-steps each), over about ``seconds``."""
    fn()  # warm-up (and compilation)
    sync(device)
    calls, start = 0, time.perf_counter()
    while True:
        fn()
        calls += 1
        if calls >= 3:
            sync(device)
            if time.perf_counter() - start >= seconds:
                break
    return calls * per_call / (time.perf_counter() - start)


def env_stepper(batch: int, device: torch.device, compiled: bool) -> Callable[[], None]:
    """``step_and_maybe_reset`` of B worlds, always-IDLE (the check of actions off)."""
    env = TensorHighwayEnv("highway-fast-v0", num_envs=batch, seed=0, device=device,
                           check_actions=False)  # fmt: skip
    if compiled:
        env.compile(dense=True, dynamic=True)  # one compilation for every B
    td = env.reset()
    action = torch.full((batch,), IDLE, device=device)

    def fn() -> None:
        nonlocal td
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)

    return fn


def _advance(world, action, params):
    """One env step of B worlds and the reset of the finished ones: a pure function."""
    new, out = sim_step(world, action, params, dense=True)
    return reset_world(new, out["terminated"] | out["truncated"], params), out["observation"]


#: One compiled function for every B (``dynamic=True``: one Inductor compilation), its
#: graphs replayed by cudagraph trees (``mode="reduce-overhead"``).
_GRAPHED: dict[str, Callable] = {}


def graph_stepper(batch: int, device: torch.device) -> Callable[[], None]:
    """The pure dense step plus the reset of finished rows, compiled and CUDA-graphed.

    ``torch.compile(mode="reduce-overhead")`` rather than a hand capture with
    ``torch.cuda.graph``: the step builds small constant tensors from Python lists
    (host-to-device copies, which a stream capture refuses); Inductor makes them graph
    constants.
    """
    if "fn" not in _GRAPHED:
        _GRAPHED["fn"] = torch.compile(_advance, mode="reduce-overhead", dynamic=True)
    advance = _GRAPHED["fn"]
    env = TensorHighwayEnv("highway-fast-v0", num_envs=batch, seed=0, device=device)
    params, action = env.params, torch.full((batch,), IDLE, device=device)
    world = env._world

    def fn() -> None:
        nonlocal world
        torch.compiler.cudagraph_mark_step_begin()
        world, _ = advance(world, action, params)

    return fn


def env_rates(args: argparse.Namespace, clock: Clock, out: dict, kinds: list[str]) -> None:
    """Each of ``kinds`` at every B (the GPU-only kinds are left out on a CPU)."""
    device = torch.device(args.device)
    if device.type != "cuda":
        kinds = [k for k in kinds if k == "eager"]
    for kind in kinds:
        for i, batch in enumerate(args.sizes):
            name = f"env-steps/s {kind} B={batch}"
            # A compiled kind compiles at its first size (minutes): start it with room.
            compiles = kind != "eager" and i == 0
            if clock.left() < args.seconds * 4 + (COMPILE_SECONDS if compiles else 0):
                out[name] = "skipped: time"
                report(name, out[name])
                continue
            fn = None
            try:
                if kind == "graph":
                    fn = graph_stepper(batch, device)
                else:
                    fn = env_stepper(batch, device, compiled=kind == "compiled")
                out[name] = timed_rate(fn, batch, device, args.seconds)
            except torch.OutOfMemoryError:
                out[name] = "out of memory"
            except Exception as error:  # noqa: BLE001 - a failed part must not end the run
                out[name] = f"failed: {type(error).__name__}: {str(error)[:200]}"
            finally:
                fn = None
                if device.type == "cuda":
                    torch.cuda.empty_cache()
            report(name, out[name])


def planner_rate(args: argparse.Namespace, clock: Clock, out: dict) -> None:
    from torchrl_grpo.branching import LookaheadPolicy
    from torchrl_grpo.modules import make_scripted_policy

    name = f"planner episodes/s ({args.planner_worlds} worlds, horizon {args.horizon})"
    if clock.left() < 30:
        out[name] = "skipped: time"
        report(name, out[name])
        return
    worlds, device = args.planner_worlds, torch.device(args.device)
    try:
        driven = TensorHighwayEnv(num_envs=worlds, seed=1, device=device, return_state=True)
        sim = TensorHighwayEnv(num_envs=worlds * 5, seed=2, device=device)
        planner = LookaheadPolicy(sim, make_scripted_policy("slower"), horizon=args.horizon)
        # Driven as training drives (step_and_maybe_reset): env.rollout's own auto-reset
        # hands the planner the reset's stale state and is refused.
        td = driven.reset()
        finished = torch.zeros(worlds, dtype=torch.bool, device=device)
        start = time.perf_counter()
        for _ in range(31):  # highway-fast-v0's episodes last 30 steps at most
            td = planner(td)
            out_td, td = driven.step_and_maybe_reset(td)
            finished |= out_td["next", "done"].reshape(worlds)
        sync(device)
        elapsed = time.perf_counter() - start
        out[name] = int(finished.sum()) / elapsed
        out["planner episodes finished"] = int(finished.sum())
        out["planner planned env-steps/s"] = planner.frames / elapsed
        report("planner planned env-steps/s", out["planner planned env-steps/s"])
    except Exception as error:  # noqa: BLE001
        out[name] = f"failed: {type(error).__name__}: {str(error)[:200]}"
    report(name, out[name])


def training_rate(args: argparse.Namespace, clock: Clock, out: dict) -> None:
    from torchrl_grpo.training import Trainer, compose_config

    name = f"training frames/s (recipe, {args.train_frames} frames, end to end)"
    if clock.left() < 30 or args.train_frames <= 0:
        out[name] = "skipped: time" if args.train_frames > 0 else "skipped"
        report(name, out[name])
        return
    overrides = [
        f"device={args.device}",
        "env.backend=tensor",
        "logger=none",
        f"experiment.total_frames={args.train_frames}",
        "experiment.eval_every=0",
        "experiment.final_eval_episodes=0",
        *args.train_override,
    ]
    try:
        cfg = compose_config(overrides)
        with tempfile.TemporaryDirectory() as run_dir:
            start = time.perf_counter()
            result = Trainer(cfg, run_dir=run_dir).train()
            elapsed = time.perf_counter() - start
        out[name] = result.frames / elapsed
        out["training frames"] = int(result.frames)
    except Exception as error:  # noqa: BLE001
        out[name] = f"failed: {type(error).__name__}: {str(error)[:300]}"
    report(name, out[name])


def report(name: str, value: object) -> None:
    text = f"{value:,.0f}" if isinstance(value, float) else str(value)
    print(f"  {name}: {text}", flush=True)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="default: 65,536 .. 1M")
    parser.add_argument("--seconds", type=float, default=3.0, help="timing per figure")
    parser.add_argument("--planner-worlds", type=int, default=1024)
    parser.add_argument("--horizon", type=int, default=4)
    parser.add_argument("--train-frames", type=int, default=100_000)
    parser.add_argument("--train-override", nargs="*", default=[], help="more config overrides")
    parser.add_argument("--budget", type=float, default=420.0, help="seconds for the whole run")
    parser.add_argument("--json", default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("--device cuda, but torch finds no CUDA device (use --device cpu)")
    args.sizes = args.sizes or (GPU_SIZES if args.device.startswith("cuda") else [64])
    clock = Clock(args.budget)
    out: dict = {"device": torch.cuda.get_device_name() if args.device != "cpu" else "cpu"}
    print(f"bench_gpu on {out['device']}, torch {torch.__version__}", flush=True)
    # The cheap figures first; the compilations (minutes) last, cut by the budget.
    env_rates(args, clock, out, ["eager"])
    planner_rate(args, clock, out)
    training_rate(args, clock, out)
    env_rates(args, clock, out, ["graph", "compiled"])
    out["seconds"] = round(time.perf_counter() - clock.start, 1)
    report("seconds", out["seconds"])
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
