"""Where one TensorHighwayEnv step's time goes: ops per step and per substep, time per stage.

Usage: ``taskset -c 0 python benchmarks/profile_tensor_env.py [--sizes 1024 8192]
[--steps 20] [--threads 1] [--native]``

With ``--native`` the env steps in C++ (``TensorHighwayEnv(native=True)``) and the stages
are the C++ call (the substeps and the observation), the reward and outputs that stay
in torch, and the reset path.

For each batch size B, highway-fast-v0 in float32, always-IDLE, stepped as training steps
it (``env.step_and_maybe_reset``, finished rows reset), it prints:

* ATen ops per env step and per substep (counted by a ``TorchDispatchMode``: each op
  the dispatcher runs once, however many it calls inside), and how many of the step's
  ops the reset path and the TorchRL plumbing add;
* ``torch.profiler``'s CPU time per stage of the simulator, each stage a
  ``record_function`` range around the functions named in the table (inclusive time,
  averaged per env step); ``rest`` is the step's time outside every stage (TorchRL's
  ``step_and_maybe_reset``, ``step_mdp``, the env's output TensorDicts, the action check);
* the reset path's share of a step: ``step_and_maybe_reset`` against ``env.step`` alone
  (the rows never reset), timed in alternating blocks outside the profiler.

The stages are wrapped by replacing the names :mod:`torchrl_grpo.sim.simulate` and the
env module imported, in this process only.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import time
from collections import Counter
from collections.abc import Callable

import torch
from torch.profiler import ProfilerActivity, profile, record_function
from torch.utils._python_dispatch import TorchDispatchMode

import torchrl_grpo.sim.native as native
import torchrl_grpo.sim.simulate as simulate
from torchrl_grpo.envs import TensorHighwayEnv

IDLE = 1
# (label, module, name): the functions each stage wraps, in the order a step calls them.
STAGES = (
    ("neighbours (lane index)", simulate, "lane_index"),
    ("IDM (drivers' accelerations)", simulate, "drivers_of"),
    ("MOBIL (lane changes)", simulate, "lane_change_policy"),
    ("steering + meta-action", simulate, "steering_control"),
    ("kinematics", simulate, "step_vehicles"),
    ("collision", simulate, "collide"),
    ("observation", simulate, "observe"),
    ("reward", simulate, "reward"),
    ("reset path (env._reset)", TensorHighwayEnv, "_reset"),
)
# With --native: the C++ call's range holds the reward's (subtracted when printed).
NATIVE_STAGES = (
    ("C++: substeps and observation", native, "_run"),
    ("reward and outputs (torch)", native, "observe_world"),
    ("reset path (env._reset)", TensorHighwayEnv, "_reset"),
)
STEP = "env.step_and_maybe_reset"
SUBSTEP = "substep"


class OpCounter(TorchDispatchMode):
    """Counts the ATen ops dispatched while active."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[str(func.overloadpacket.__name__)] += 1
        return func(*args, **(kwargs or {}))


def wrap_stages(stages: tuple) -> None:
    """Put a ``record_function`` range around each stage's function (and each substep)."""

    in_reset = [False]

    def ranged(label: str, fn: Callable) -> Callable:
        # Inside the reset path, the stages it calls (observation, reward) count as reset.
        resets = label == stages[-1][0]

        @functools.wraps(fn)
        def inner(*args, **kwargs):
            if in_reset[0]:
                return fn(*args, **kwargs)
            with record_function(label):
                in_reset[0] = resets
                try:
                    return fn(*args, **kwargs)
                finally:
                    in_reset[0] = False

        return inner

    for label, owner, name in stages:
        setattr(owner, name, ranged(label, getattr(owner, name)))
    simulate.substep = ranged(SUBSTEP, simulate.substep)
    if hasattr(simulate, "eager_stages"):
        # The default stages hold the functions themselves: rebuild them from the wrapped.
        simulate.EAGER = simulate.eager_stages()


def make(
    batch: int, native_step: bool
) -> tuple[TensorHighwayEnv, Callable[[], None], Callable[[], None]]:
    """The env and two steppers: as training steps, and ``env.step`` with no resets."""
    env = TensorHighwayEnv("highway-fast-v0", num_envs=batch, seed=0, native=native_step)
    td = env.reset()
    action = torch.full((batch,), IDLE)

    def train_step() -> None:
        nonlocal td
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)

    plain = env.reset().set("action", action)

    def step_only() -> None:
        env.step(plain)

    for _ in range(3):
        train_step()
    return env, train_step, step_only


def profile_size(batch: int, steps: int, stages: tuple) -> None:
    """Print the op counts and the stage table of one batch size."""
    native_step = stages is NATIVE_STAGES
    env, train_step, step_only = make(batch, native_step)
    counter = OpCounter()
    with counter:
        for _ in range(steps):
            train_step()
    total = sum(counter.ops.values()) / steps
    frames = env.params.time.frames
    with OpCounter() as alone:
        for _ in range(steps):
            step_only()
    plain = sum(alone.ops.values()) / steps
    pure = native.native_step if native_step else simulate.step
    with OpCounter() as sim_ops:
        world, _ = pure(env._world, torch.full((batch,), IDLE), env.params)
    sim = sum(sim_ops.ops.values())
    print(f"\nB = {batch}: ATen ops per env step (as training steps it): {total:,.0f}")
    print(f"  the simulator's pure step: {sim:,} ({sim / frames:,.0f} per substep of {frames},")
    print(f"  observation and reward included); env.step without resets: {plain:,.0f};")
    print(f"  so the reset path adds {total - plain:,.0f} and the env/TorchRL plumbing")
    print(f"  {plain - sim:,.0f}. Most frequent ops: {counter.ops.most_common(8)}")

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            with record_function(STEP):
                train_step()
    times: dict[str, float] = {}
    for event in prof.key_averages():
        times[event.key] = event.cpu_time_total / steps  # us per env step
    whole = times[STEP]
    print("\n  | stage | ms per env step | share of the step | per world (us) |")
    print("  |---|---|---|---|")
    inside = 0.0
    nested = times.get(NATIVE_STAGES[1][0], 0.0) if native_step else 0.0
    for label, _, _ in stages:
        t = times.get(label, 0.0) - (nested if label == NATIVE_STAGES[0][0] else 0.0)
        inside += t
        print(f"  | {label} | {t / 1e3:.2f} | {t / whole:.0%} | {t / batch:.2f} |")
    rest = whole - inside
    print(f"  | rest (TorchRL, env plumbing) | {rest / 1e3:.2f} | {rest / whole:.0%} | "
          f"{rest / batch:.2f} |")  # fmt: skip
    print(f"  | **whole step** | {whole / 1e3:.2f} | 100% | {whole / batch:.2f} |")

    rates: dict[str, list[float]] = {"train": [], "plain": []}
    calls = max(3, min(100, 10000 // batch))
    for _ in range(3):
        for name, fn in (("train", train_step), ("plain", step_only)):
            start = time.perf_counter()
            for _ in range(calls):
                fn()
            rates[name].append(calls * batch / (time.perf_counter() - start))
    train, plain_rate = (statistics.median(rates[k]) for k in ("train", "plain"))
    print(f"\n  env-steps/s: step_and_maybe_reset {train:,.0f}, env.step alone {plain_rate:,.0f};")
    print(f"  the reset path costs {plain_rate / train - 1:.0%} of a step without it")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 8192])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--native", action="store_true", help="the C++ step's stages")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    stages = NATIVE_STAGES if args.native else STAGES
    wrap_stages(stages)
    for batch in args.sizes:
        profile_size(batch, args.steps, stages)


if __name__ == "__main__":
    main()
