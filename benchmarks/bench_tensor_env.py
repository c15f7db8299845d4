"""TensorHighwayEnv's throughput beside HighwayEnv and EnvPool, and its snapshot cost.

Usage: ``python benchmarks/bench_tensor_env.py [--scenario highway-fast-v0] [--sizes 1 64
1024 8192] [--threads N] [--compile] [--native] [--device cpu] [--checks-only] [--highjax-python
PYTHON] [--no-highway]``

merge-v0 against HighwayEnv("merge-v0") and EnvPool's merge-v0 (a C++ port with the
spaces of highway-env's, not its dynamics), on one core then two::

    taskset -c 0 python benchmarks/bench_tensor_env.py --scenario merge-v0 --sizes 1024 \
        --peers-only --repeats 3


The issue #41 table (docs/benchmarks.md, "Peers"): one core, then two threads::

    taskset -c 0 python benchmarks/bench_tensor_env.py --sizes 1024 8192 --no-highway \
        --highjax-python /work/venv-jax/bin/python --peers-only
    python benchmarks/bench_tensor_env.py --sizes 1024 8192 --no-highway \
        --highjax-python /work/venv-jax/bin/python --peers-only

``--threads`` defaults to the cores the process may run on (``taskset`` sets them):
torch's intra-op threads, EnvPool's ``num_threads`` and XLA's threads all get that many.

For each batch size B, one run measures env steps per second of highway-fast-v0 in
float32, side by side in alternating blocks (so that both sides of a ratio see the same
machine load):

* ``TensorHighwayEnv(num_envs=B)`` stepped through TorchRL's ``env.step`` (what a user
  gets), always-IDLE actions, worlds reset as their episodes end;
* ``HighwayEnv`` (highway-env itself) stepped in this one process;
* EnvPool's C++ ``highway-fast-v0`` with ``num_envs=B`` and ``num_threads`` = the
  threads, when ``envpool`` is installed (``pip install -e ".[bench]"``); it resets
  finished envs itself;
* HighJax 0.1.0 (a JAX port) configured like highway-fast-v0, ``jit(vmap(step))`` with
  its own auto-reset, when ``--highjax-python`` names a python that has it: it runs in
  that python as a subprocess (``benchmarks/highjax_worker.py``), timed block by block
  in turn with the others.

Goals (issue #17): at B = 1,024 on 2 CPU cores, TensorHighwayEnv >= 200 x HighwayEnv;
EnvPool's rate is the aim (the ratio is reported). Also reported: ``get_state`` plus a
restore of B = 1,024 worlds against one ``copy.deepcopy`` of a highway-env env, and the
state's bytes per world. With ``--compile``, the same figures for ``compile=True``; with
``--native``, for the C++ step (``env.native()``).

The checks' costs, each on against off in alternating blocks (``--checks-only`` prints
only these): a restore of B = 1,024 worlds with ``check_states=True`` against ``False``
(and the value check's own time, :meth:`TensorHighwayEnv.validate_state`); at each B,
``env.step_and_maybe_reset`` with ``check_actions=True`` against ``False``, and the
action check alone against one step; and HighwayEnv's step with its action check on
against off. The state figures run against any checkout (``PYTHONPATH=<checkout> python
benchmarks/bench_tensor_env.py --checks-only --sizes``: no sizes, the state figures
alone), so that a change to the state check is measured before and after.
"""

from __future__ import annotations

import argparse
import atexit
import copy
import functools
import inspect
import os
import statistics
import time
from collections.abc import Callable

import torch
from claims import claim
from peer_steppers import IDLE, envpool_stepper, highjax_stepper, highway_stepper
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv


def rate(step: Callable[[], None], calls: int, per_call: int) -> float:
    """Env steps per second over ``calls`` calls of ``step`` (each ``per_call`` env steps)."""
    start = time.perf_counter()
    for _ in range(calls):
        step()
    return calls * per_call / (time.perf_counter() - start)


def interleaved(
    runs: dict[str, tuple[Callable[[], None], int, int]], repeats: int
) -> dict[str, float]:
    """Median rate of each run, measured in alternating blocks."""
    out: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(repeats):
        for name, (step, calls, per_call) in runs.items():
            out[name].append(rate(step, calls, per_call))
    return {k: statistics.median(v) for k, v in out.items()}


def tensor_stepper(
    batch: int,
    compile: bool,
    device: str,
    scenario: str = "highway-fast-v0",
    native: bool = False,
    **env_kwargs,
) -> Callable[[], None]:
    """One ``env.step`` of B worlds, with TorchRL's auto-reset of finished rows.

    ``env_kwargs`` go to TensorHighwayEnv (such as ``check_actions``).
    """
    env = TensorHighwayEnv(
        scenario, num_envs=batch, seed=0, compile=compile, device=device, **env_kwargs
    )
    if native:
        env.native()
    td = env.reset()
    action = torch.full((batch,), IDLE, device=env.device)

    def step() -> None:
        nonlocal td
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)

    step()  # warm-up (and compilation)
    if device == "cuda":
        sync = torch.cuda.synchronize

        def synced() -> None:
            step()
            sync()

        return synced
    return step


def _shard(batch: int, seed: int) -> TensorHighwayEnv:
    """One shard of the worlds (a module-level function: ParallelEnv pickles it)."""
    return TensorHighwayEnv("highway-fast-v0", num_envs=batch, seed=seed)


def shard_stepper(batch: int, shards: int) -> Callable[[], None]:
    """B worlds as ``shards`` processes of B / shards worlds, one torch thread each.

    TorchRL's ``ParallelEnv`` (batch ``[shards, B / shards]``), stepped with
    ``step_and_maybe_reset``: one process per core instead of intra-op threads.
    """
    from torchrl.envs import ParallelEnv

    makers = [functools.partial(_shard, batch // shards, seed) for seed in range(shards)]
    env = ParallelEnv(shards, makers, num_threads=1, num_sub_threads=1)
    atexit.register(env.close)
    td = env.reset()
    action = torch.full((shards, batch // shards), IDLE)

    def step() -> None:
        nonlocal td
        td.set("action", action)
        _, td = env.step_and_maybe_reset(td)

    step()
    return step


def snapshot_cost(batch: int, repeats: int) -> None:
    """``get_state`` + restore of B worlds against one deepcopy of a highway-env env."""
    env = TensorHighwayEnv("highway-fast-v0", num_envs=batch, seed=0)
    env.reset()
    hw = HighwayEnv("highway-fast-v0", seed=0)
    hw.reset()
    core = hw.gym_env.unwrapped

    def snap() -> None:
        state = env.get_state()
        env.reset(TensorDict(state=state, batch_size=[batch]), set_state=True)

    times: dict[str, list[float]] = {"tensor": [], "deepcopy": []}
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(10):
            snap()
        times["tensor"].append((time.perf_counter() - start) / 10)
        start = time.perf_counter()
        for _ in range(10):
            copy.deepcopy(core)
        times["deepcopy"].append((time.perf_counter() - start) / 10)
    tensor, deep = statistics.median(times["tensor"]), statistics.median(times["deepcopy"])
    what = f"get_state + restore of {batch} worlds / one deepcopy of a highway-env env"
    claim(what, tensor / deep, note=f"{tensor * 1e3:.2f} ms vs {deep * 1e3:.2f} ms")
    state = env.get_state()
    size = sum(t.numel() * t.element_size() for t in state.values(True, True))
    claim("state bytes per world (highway-fast-v0, float32)", size / batch)


def state_check_cost(batch: int, repeats: int) -> None:
    """A restore of B worlds with ``check_states`` on against off, and the check alone."""
    envs = {on: TensorHighwayEnv(num_envs=batch, seed=0, check_states=on) for on in (True, False)}
    state = envs[True].get_state()
    restore = TensorDict(state=state, batch_size=[batch])

    def timed(call: Callable[[], object]) -> float:
        start = time.perf_counter()
        for _ in range(20):
            call()
        return (time.perf_counter() - start) / 20

    times: dict[str, list[float]] = {"on": [], "off": [], "check": []}
    for _ in range(repeats):
        for on, env in envs.items():
            times["on" if on else "off"].append(
                timed(lambda env=env: env.reset(restore.clone(False), set_state=True))
            )
        times["check"].append(timed(lambda: envs[True].validate_state(state)))
    on, off, check = (statistics.median(times[k]) for k in ("on", "off", "check"))
    claim(
        f"restore of {batch} worlds: check_states=True / False time",
        on / off,
        note=f"{on * 1e3:.3f} ms vs {off * 1e3:.3f} ms",
    )
    claim(f"validate_state of {batch} worlds (ms, the value check included)", check * 1e3)


def action_check_cost(sizes: list[int], device: str, repeats: int) -> None:
    """``step_and_maybe_reset`` with ``check_actions`` on against off, at each B."""
    if "check_actions" not in inspect.signature(TensorHighwayEnv.__init__).parameters:
        print("  (this checkout has no check_actions: no action-check figures)")
        return
    from torchrl_grpo.envs.core.action_validation import check_action

    for batch in sizes:
        calls = max(2, min(200, 20000 // batch))
        runs = {
            f"check_actions={on}": (
                tensor_stepper(batch, False, device, check_actions=on),
                calls,
                batch,
            )
            for on in (True, False)
        }
        rates = interleaved(runs, repeats)
        on, off = rates["check_actions=True"], rates["check_actions=False"]
        claim(
            f"TensorHighwayEnv B={batch}, {device}: check_actions=True / False env-steps/s",
            on / off,
            note=f"{on:,.0f}/s vs {off:,.0f}/s",
        )
        # The check alone, against the step it guards (the ratio above is within noise).
        env = TensorHighwayEnv(num_envs=batch, device=device)
        action = torch.full((batch,), IDLE, device=env.device)
        calls_check = 2000
        start = time.perf_counter()
        for _ in range(calls_check):
            check_action(action, env.action_spec, "bench", batch_dims=1)
        alone = (time.perf_counter() - start) / calls_check
        claim(
            f"TensorHighwayEnv B={batch}, {device}: the action check / one step, time",
            alone / (batch / off),
            note=f"{alone * 1e6:.1f} us of {batch / off * 1e6:,.0f} us",
        )
    runs = {f"{on}": (highway_stepper(check_actions=on), 30, 1) for on in (True, False)}
    rates = interleaved(runs, repeats)
    claim(
        "HighwayEnv: check_actions=True / False env-steps/s",
        rates["True"] / rates["False"],
        note=f"{rates['True']:,.0f}/s vs {rates['False']:,.0f}/s",
    )


def peer_rates(
    batch: int, args: argparse.Namespace, hw: Callable[[], None] | None
) -> dict[str, float]:
    """Median env-steps/s of TensorHighwayEnv and each installed peer at B, interleaved."""
    # Blocks of about a second each: fewer calls for larger batches.
    calls = max(2, min(200, 20000 // batch))
    runs = {"tensor": (tensor_stepper(batch, False, args.device, args.scenario), calls, batch)}
    if args.compile:
        runs["compiled"] = (tensor_stepper(batch, True, args.device), calls, batch)
    if args.native:
        native = tensor_stepper(batch, False, args.device, args.scenario, native=True)
        runs["native"] = (native, calls, batch)
    if args.shards > 1:
        runs["shards"] = (shard_stepper(batch, args.shards), calls, batch)
    if hw is not None:
        runs["highway"] = (hw, 30, 1)
    pool = envpool_stepper(batch, args.threads, args.scenario)
    if pool is not None:
        runs["envpool"] = (pool, calls, batch)
    timed = {}
    if args.highjax_python and args.scenario == "highway-fast-v0":  # its port of that one
        timed["highjax"] = highjax_stepper(args.highjax_python, batch, args.threads)
    out: dict[str, list[float]] = {k: [] for k in (*runs, *timed)}
    for _ in range(args.repeats):
        for name, (step, n, per_call) in runs.items():
            out[name].append(rate(step, n, per_call))
        for name, block in timed.items():
            out[name].append(block())
    return {k: statistics.median(v) for k, v in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    # "--sizes" with no value: with --checks-only, the state check's figures alone.
    parser.add_argument("--sizes", type=int, nargs="*", default=[1, 64, 1024, 8192])
    cores = len(os.sched_getaffinity(0))
    parser.add_argument("--threads", type=int, default=cores, help="default: the cores")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--native", action="store_true", help="also the C++ step (env.native())")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--scenario", default="highway-fast-v0", help="or another of TENSOR_SCENARIOS"
    )
    parser.add_argument("--checks-only", action="store_true", help="only the checks' costs")
    parser.add_argument("--highjax-python", help="a python with highjax: run it as a peer")
    parser.add_argument("--no-highway", action="store_true", help="leave highway-env out")
    parser.add_argument("--peers-only", action="store_true", help="no snapshot/check figures")
    parser.add_argument(
        "--shards", type=int, default=0, help="also B worlds as this many 1-thread processes"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.checks_only:
        state_check_cost(1024, args.repeats)
        if args.sizes:
            action_check_cost(args.sizes, args.device, args.repeats)
        return
    hw = None if args.no_highway else highway_stepper(args.scenario)
    for batch in args.sizes:
        rates = peer_rates(batch, args, hw)
        where = (
            f"{args.scenario}, B={batch}, {args.threads} threads on {cores} cores, {args.device}"
        )
        note = ", ".join(f"{k} {v:,.0f}/s" for k, v in rates.items())
        load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
        print(f"  {where}: {note} (load average {load})")
        for name, value in rates.items():
            claim(f"{where}: {name} env-steps/s", value)
        if "highway" in rates:
            # The goal of issue #17, set for highway-fast-v0 only.
            fast = args.scenario == "highway-fast-v0"
            goal = ">=200" if fast and batch == 1024 and args.device == "cpu" else None
            claim(
                f"{where}: TensorHighwayEnv / HighwayEnv env-steps/s",
                rates["tensor"] / rates["highway"],
                goal,
                note=note,
            )
        ours = [("tensor", "TensorHighwayEnv")]
        if "compiled" in rates:
            claim(f"{where}: compiled / eager env-steps/s", rates["compiled"] / rates["tensor"])
            ours.append(("compiled", "compiled TensorHighwayEnv"))
        if "native" in rates:
            claim(f"{where}: C++ / tensor env-steps/s", rates["native"] / rates["tensor"])
            ours.append(("native", "TensorHighwayEnv with the C++ step"))
        if "shards" in rates:
            ours.append(("shards", f"TensorHighwayEnv in {args.shards} shards"))
        for name, who in ours:
            for peer, label in (("envpool", "EnvPool"), ("highjax", "HighJax")):
                if peer in rates:
                    claim(
                        f"{where}: {who} / {label} env-steps/s",
                        rates[name] / rates[peer],
                        note=f"{rates[name]:,.0f}/s vs {rates[peer]:,.0f}/s",
                    )
    if args.peers_only:
        return
    snapshot_cost(1024, args.repeats)
    state_check_cost(1024, args.repeats)
    action_check_cost(args.sizes, args.device, args.repeats)


if __name__ == "__main__":
    main()
