"""Env overhead and snapshot cost, as ratios measured side by side in one run.

Usage: ``python benchmarks/bench_env.py [--scenarios highway-fast-v0 merge-v0] [--repeats 7]``

Each figure is the median of interleaved blocks (A, B, A, B, ...), so that both sides of
a ratio see the same machine load. Goals (issue #2):

* HighwayEnv step throughput / raw gymnasium step throughput >= 0.97
* (get_state + restore) / copy.deepcopy(env.unwrapped)        <= 0.7
* restore / (reset + replay of a 5-step prefix)                <= 0.01
* state bytes / pickled env bytes                              <= 1.0
"""

from __future__ import annotations

import argparse
import copy
import pickle
import statistics
import time
from collections.abc import Callable

import gymnasium as gym
import torch
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv

IDLE = 1


def per_call(fn: Callable[[], object], calls: int) -> float:
    """Seconds per call of ``fn`` over ``calls`` calls."""
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls


def interleaved(a: Callable[[], object], b: Callable[[], object], calls: int, repeats: int):
    """Median seconds per call of ``a`` and of ``b``, measured in alternating blocks."""
    ta, tb = [], []
    for _ in range(repeats):
        ta.append(per_call(a, calls))
        tb.append(per_call(b, calls))
    return statistics.median(ta), statistics.median(tb)


def row(name: str, value: float, goal: str, met: bool) -> None:
    print(f"  {name:<48} {value:10.4f}   goal {goal:<7} {'MET' if met else 'NOT MET'}")


def bench(scenario: str, repeats: int) -> None:
    print(f"{scenario}")
    env = HighwayEnv(scenario, seed=0)
    raw = gym.make(scenario, disable_env_checker=True)
    raw.reset(seed=0)
    env.reset()
    action = TensorDict(action=torch.tensor(IDLE))

    def step_ours() -> None:
        if env.step(action.clone())["next", "done"]:
            env.reset()

    def step_raw() -> None:
        _, _, terminated, truncated, _ = raw.step(IDLE)
        if terminated or truncated:
            raw.reset()

    t_ours, t_raw = interleaved(step_ours, step_raw, calls=20, repeats=repeats)
    ratio = t_raw / t_ours
    print(f"  step: HighwayEnv {1 / t_ours:8.1f}/s, raw gymnasium {1 / t_raw:8.1f}/s")
    row("HighwayEnv / raw step throughput", ratio, ">=0.97", ratio >= 0.97)

    env.reset()
    for _ in range(5):
        env.step(action.clone())
    state = env.get_state()
    td = TensorDict(state=state)

    def snapshot_restore() -> None:
        env.get_state()
        env.reset(td, set_state=True)

    def codec_round_trip() -> None:
        env.codec.decode(env.gym_env, env.codec.encode(env.gym_env))

    def deepcopy() -> None:
        copy.deepcopy(env.gym_env.unwrapped)

    t_snap, t_copy = interleaved(snapshot_restore, deepcopy, calls=50, repeats=repeats)
    t_codec, _ = interleaved(codec_round_trip, deepcopy, calls=50, repeats=repeats)
    print(
        f"  get_state + reset(set_state) {t_snap * 1e3:.3f} ms, codec encode + decode "
        f"{t_codec * 1e3:.3f} ms, deepcopy {t_copy * 1e3:.3f} ms"
    )
    row(
        "(get_state + restore) / deepcopy, via TorchRL reset",
        t_snap / t_copy,
        "<=0.7",
        t_snap / t_copy <= 0.7,
    )
    row(
        "(encode + decode) / deepcopy, codec alone",
        t_codec / t_copy,
        "<=0.7",
        t_codec / t_copy <= 0.7,
    )

    def restore() -> None:
        env.reset(td, set_state=True)

    def reset_replay() -> None:
        raw.reset(seed=0)
        for _ in range(5):
            raw.step(IDLE)

    t_restore, t_replay = interleaved(restore, reset_replay, calls=5, repeats=repeats)
    print(f"  restore {t_restore * 1e3:.3f} ms, reset + 5-step replay {t_replay * 1e3:.1f} ms")
    row(
        "restore / (reset + replay 5 steps)",
        t_restore / t_replay,
        "<=0.01",
        t_restore / t_replay <= 0.01,
    )

    state_bytes = sum(t.numel() * t.element_size() for t in state.values(True, True))
    pickled = len(pickle.dumps(env.gym_env.unwrapped))
    print(f"  state {state_bytes} bytes, pickled env {pickled} bytes")
    row("state bytes / pickled env bytes", state_bytes / pickled, "<=1.0", state_bytes <= pickled)
    env.close()
    raw.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["highway-fast-v0", "merge-v0"])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    for scenario in args.scenarios:
        bench(scenario, args.repeats)


if __name__ == "__main__":
    main()
