"""Everything a GPU session measures, in one run of under 8 minutes on one H200.

    python benchmarks/bench_gpu.py --checkpoints ckpt  # cuda, B = 65,536 .. 1,048,576
    python benchmarks/bench_gpu.py --device cpu --sizes 64 --train-frames 256 \\
        --planner-worlds 2 --budget 120                # the CPU smoke run (tests/test_bench_gpu.py)

Each part is skipped (and says so) once ``--budget`` seconds are spent, so that the run
ends in time; training, last, runs for what is left. The parts:

1. env-steps/s of highway-fast-v0, float32, always-IDLE, finished worlds reset, at each B:
   * ``eager``: ``TensorHighwayEnv.step_and_maybe_reset`` (what training calls; on a
     GPU the step takes its dense, sync-free path);
   * ``compiled``: the simulator without TorchRL's per-step Python: one substep and the
     step's outputs with the reset of finished rows
     (:func:`~torchrl_grpo.sim.reset.reset_world`, sync-free on a GPU) each through
     ``torch.compile(dynamic=True)`` (GPU only). The substep is compiled alone and called
     ``frames`` times: the whole step unrolls its five substeps into one graph, which
     Inductor had not finished lowering after five minutes on one CPU core, where one
     substep compiles in 92 s (44 s with static shapes);
   * ``graph``: those compiled kernels captured once per B in a CUDA graph
     (``torch.cuda.graph``) that also copies the new worlds over its inputs, and
     replayed: no launch cost left (GPU only).
   Every B of one kind runs before the next kind; a size that runs out of memory is
   reported as such.
2. The branch-as-rows lookahead planner
   (:class:`~torchrl_grpo.branching.LookaheadPolicy` on a TensorHighwayEnv, every
   action's branch a row of one batched rollout): ``--planner-worlds`` episodes of at
   most 30 steps driven at once, horizon ``--horizon``, base policy ``slower``:
   episodes/s and planned env-steps/s.
3. The recipe (``scripts/train.py``'s default config, GRPO with branching, on the
   tensor simulator, on ``--device``) for ``--train-frames`` frames (default: the
   recipe's 2M) or ``--train-seconds``, whichever comes first, no evaluation: training
   frames/s end to end (collection, policy and learner), and the frames and seconds at
   every ``--milestone-frames``. With ``--checkpoints DIR``, the policy at each milestone
   is saved there (``recipe_<frames>.pt``), to be evaluated on highway-env's episodes
   elsewhere (``bench_crash_rates.py --checkpoint``): minutes to a return.

It prints one ``NAME: VALUE`` line per figure and, with ``--json``, writes them all.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch.utils._pytree import tree_flatten, tree_leaves, tree_unflatten

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.sim.reset import reset_world
from torchrl_grpo.sim.simulate import observe_world, substep
from torchrl_grpo.sim.state import World
from torchrl_grpo.training.hooks import Hook

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


def env_stepper(batch: int, device: torch.device) -> Callable[[], None]:
    """``step_and_maybe_reset`` of B worlds, always-IDLE (the check of actions off)."""
    env = TensorHighwayEnv("highway-fast-v0", num_envs=batch, seed=0, device=device,
                           check_actions=False)  # fmt: skip
    td = env.reset()
    action = torch.full((batch,), IDLE, device=device)

    def fn() -> None:
        nonlocal td
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)

    return fn


def _finish(world: World, params) -> World:
    """The step's outputs and the reset of the finished worlds (a pure function)."""
    out = observe_world(world, params)
    return reset_world(world, out["terminated"] | out["truncated"], params)


def advance_fn(substep_fn: Callable, finish_fn: Callable, action, params) -> Callable:
    """One env step of B worlds plus the reset of the finished ones: ``world -> world``.

    ``substep_fn`` and ``finish_fn`` are :func:`~torchrl_grpo.sim.simulate.substep` and
    :func:`_finish`, eager or compiled; eager, it is ``simulate.step`` plus
    ``reset_world`` (tests/test_bench_gpu.py holds it to their bits).
    """
    frames, step_time = params.time.frames, params.time.step_time

    def advance(world: World) -> World:
        world = world._replace(time=world.time + step_time)
        for _ in range(frames):
            world = substep_fn(world, action, params, True)
        return finish_fn(world, params)

    return advance


def tensors(world: World) -> list[torch.Tensor]:
    """The world's tensors, nested tables included (highway's empty routes left out)."""
    return [t for t in tree_leaves(world) if t is not None]


def returning_tensors(fn: Callable[..., World]) -> Callable[..., World]:
    """``fn`` compiled, its world passed out as tensors and rebuilt outside.

    torch 2.11's compiled functions return an empty ``World`` (a named tuple with
    defaults) in place of the one built inside; 2.13's return it whole.
    """
    compiled = torch.compile(lambda *args: tuple(tensors(fn(*args))), dynamic=True)

    def call(world: World, *args) -> World:
        leaves, spec = tree_flatten(world)
        new = iter(compiled(world, *args))
        return tree_unflatten([None if x is None else next(new) for x in leaves], spec)

    return call


#: The compiled substep and finish, shared by every B and by both kinds (``dynamic=True``:
#: one Inductor compilation each).
_COMPILED: dict[str, Callable] = {}


def pure_stepper(batch: int, device: torch.device, graph: bool) -> Callable[[], None]:
    """The compiled pure step of B worlds, replayed from a CUDA graph if ``graph``."""
    if not _COMPILED:
        _COMPILED["substep"] = returning_tensors(substep)
        _COMPILED["finish"] = returning_tensors(_finish)
    env = TensorHighwayEnv("highway-fast-v0", num_envs=batch, seed=0, device=device)
    action = torch.full((batch,), IDLE, device=device)
    advance = advance_fn(_COMPILED["substep"], _COMPILED["finish"], action, env.params)
    world = env._world
    if not graph:

        def fn() -> None:
            nonlocal world
            world = advance(world)

        return fn
    # Warm up on a side stream (compilation, the allocator), as torch.cuda.graph asks.
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(2):
            world = advance(world)
    torch.cuda.current_stream().wait_stream(side)
    captured = torch.cuda.CUDAGraph()
    with torch.cuda.graph(captured):
        new = advance(world)
        for old, fresh in zip(tensors(world), tensors(new), strict=True):
            old.copy_(fresh)  # each replay steps the worlds in place
    return captured.replay


def env_rates(args: argparse.Namespace, clock: Clock, out: dict, kinds: list[str]) -> None:
    """Each of ``kinds`` at every B (the GPU-only kinds are left out on a CPU)."""
    device = torch.device(args.device)
    if device.type != "cuda":
        kinds = [k for k in kinds if k == "eager"]
    for kind in kinds:
        for i, batch in enumerate(args.sizes):
            name = f"env-steps/s {kind} B={batch}"
            # The compiled kind compiles at its first size (minutes): start it with room.
            compiles = kind == "compiled" and i == 0
            if clock.left() < args.seconds * 4 + (COMPILE_SECONDS if compiles else 0):
                out[name] = "skipped: time"
                report(name, out[name])
                continue
            fn = None
            try:
                if kind == "eager":
                    fn = env_stepper(batch, device)
                else:
                    fn = pure_stepper(batch, device, graph=kind == "graph")
                out[name] = timed_rate(fn, batch, device, args.seconds)
            except torch.OutOfMemoryError:
                out[name] = "out of memory"
            except Exception as error:  # noqa: BLE001 - a failed part must not end the run
                out[name] = f"failed: {type(error).__name__}: {str(error)[:200]}"
                log.exception("%s", name)
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
        log.exception("%s", name)
    report(name, out[name])


class Milestones(Hook):
    """Notes the frames and seconds every ``every`` frames and at the end, saves the
    policy there, and stops the run after ``seconds`` of training (as Ctrl-C would)."""

    phase = "milestones"

    def __init__(self, every: int, seconds: float, save_to: Path | None) -> None:
        self.every, self.seconds, self.save_to = every, seconds, save_to
        self.next = every
        self.curve: list[list[float]] = []

    def due(self, trainer, batch) -> bool:
        return True

    def on_iteration(self, trainer, batch, result) -> dict:
        seconds = trainer.wall_seconds()
        if seconds >= self.seconds:
            trainer.stop_requested = True
        ends = trainer.stop_requested or trainer.frames >= trainer.cfg.experiment.total_frames
        if trainer.frames >= self.next or ends:
            while self.next <= trainer.frames:
                self.next += self.every
            self.curve.append([trainer.frames, round(seconds, 1)])
            if self.save_to is not None:
                name = f"recipe_{trainer.frames}.pt"
                shutil.copy(trainer.save(name=name), self.save_to / name)
        return {}


def training_rate(args: argparse.Namespace, clock: Clock, out: dict) -> None:
    from torchrl_grpo.training import Trainer, compose_config

    name = "training frames/s (recipe, end to end)"
    if clock.left() < 30 or args.train_frames == 0:
        out[name] = "skipped: time" if args.train_frames != 0 else "skipped"
        report(name, out[name])
        return
    overrides = [
        f"device={args.device}",
        "env.backend=tensor",
        "logger=none",
        "experiment.eval_every=0",
        "experiment.final_eval_episodes=0",
        "experiment.checkpoint_every=0",
        *([f"experiment.total_frames={args.train_frames}"] if args.train_frames else []),
        *args.train_override,
    ]
    seconds = min(args.train_seconds, clock.left() - 20)
    save_to = Path(args.checkpoints) if args.checkpoints else None
    if save_to is not None:
        save_to.mkdir(parents=True, exist_ok=True)
    try:
        cfg = compose_config(overrides)
        milestones = Milestones(args.milestone_frames, seconds, save_to)
        with tempfile.TemporaryDirectory() as run_dir:
            start = time.perf_counter()
            result = Trainer(cfg, run_dir=run_dir, hooks=[milestones]).train()
            elapsed = time.perf_counter() - start
        out[name] = result.frames / elapsed
        out["training frames"] = int(result.frames)
        out["training seconds"] = round(elapsed, 1)
        out["training stopped by --train-seconds"] = bool(result.interrupted)
        out["training milestones [frames, seconds]"] = milestones.curve
        report("training milestones [frames, seconds]", milestones.curve)
    except Exception as error:  # noqa: BLE001
        out[name] = f"failed: {type(error).__name__}: {str(error)[:300]}"
        log.exception("%s", name)
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
    parser.add_argument("--train-frames", type=int, default=None, help="default: the recipe's")
    parser.add_argument("--train-seconds", type=float, default=200.0, help="training's cap")
    parser.add_argument("--milestone-frames", type=int, default=500_000)
    parser.add_argument("--checkpoints", default=None, help="save the policy at milestones here")
    parser.add_argument("--train-override", nargs="*", default=[], help="more config overrides")
    parser.add_argument("--budget", type=float, default=500.0, help="seconds for the whole run")
    parser.add_argument("--json", default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("--device cuda, but torch finds no CUDA device (use --device cpu)")
    args.sizes = args.sizes or (GPU_SIZES if args.device.startswith("cuda") else [64])
    clock = Clock(args.budget)
    out: dict = {"device": torch.cuda.get_device_name() if args.device != "cpu" else "cpu"}
    print(f"bench_gpu on {out['device']}, torch {torch.__version__}", flush=True)
    # The simulator's rates first (the compilation takes minutes), then the planner, then
    # training for what the budget leaves (--train-seconds at most).
    env_rates(args, clock, out, ["eager", "compiled", "graph"])
    planner_rate(args, clock, out)
    training_rate(args, clock, out)
    out["seconds"] = round(time.perf_counter() - clock.start, 1)
    report("seconds", out["seconds"])
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
