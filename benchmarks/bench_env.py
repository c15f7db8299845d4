"""Env overhead and snapshot cost, as ratios measured side by side in one run.

Usage: ``python benchmarks/bench_env.py [--scenarios highway-fast-v0 merge-v0] [--repeats 7]``

Each figure is the median of interleaved blocks (A, B, A, B, ...), so that both sides of
a ratio see the same machine load. The step throughput runs the same episodes on both
sides (same seeds, same actions, observations checked identical), in lockstep, and times
the step calls only; a second line, for information, counts the resets in. Goals (issue #2):

* HighwayEnv step throughput / raw gymnasium step throughput >= 0.97
* (get_state + restore) / copy.deepcopy(env.unwrapped)        <= 0.7
* restore / (reset + replay of a 5-step prefix)                <= 0.01
* state bytes / pickled env bytes                              <= 1.0

For information beside them: TorchRL's own ``GymEnv`` over the same scenario, measured
the same way (what any TorchRL env costs on top of this simulator); the wrapper's own
CPU per step with the simulator stubbed out; and how a restore splits between
``SnapshotEnv._reset`` and TorchRL's reset bookkeeping.
"""

from __future__ import annotations

import argparse
import copy
import pickle
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
from claims import claim
from tensordict import TensorDict
from torchrl.envs import EnvBase, GymEnv

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.envs.core.bits import leaves, nested_tensordict

IDLE = 1
MAX_STEPS = 40  # per episode; episodes that end earlier are timed to their end


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


@dataclass
class EpisodeTiming:
    """Seconds one episode cost each side: its reset, and its step calls alone."""

    steps: int = 0
    ours_reset: float = 0.0
    raw_reset: float = 0.0
    ours_steps: float = 0.0
    raw_steps: float = 0.0


def timed(fn: Callable[[], object]) -> tuple[object, float]:
    """``fn()`` and the seconds it took."""
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


def same_obs(ours: torch.Tensor, raw: np.ndarray) -> bool:
    """Whether our observation holds exactly raw gymnasium's values."""
    return np.array_equal(ours.numpy(), np.asarray(raw, dtype=np.float32))


def episode_pair(env: EnvBase, raw: gym.Env, seed: int, max_steps: int) -> EpisodeTiming:
    """Run episode ``seed`` on both envs in lockstep with IDLE actions, timing every call.

    Both sides reset with the same seed and take the same actions, and every
    observation is checked to be identical, so both simulate the same traffic: the
    difference in time is our wrapper's own cost. Calls alternate (ours first on even
    steps, raw first on odd ones), so that both sides see the same machine load (other
    jobs share the CPU) and neither always runs on caches the other just warmed.

    Raises:
        RuntimeError: the two envs diverged, so the timings would not be comparable.
    """
    # Inputs are built before the clock starts, as raw gymnasium's int action is: the
    # ratio measures env.step, not the caller's construction of its argument.
    inputs = [TensorDict(action=torch.tensor(IDLE)) for _ in range(max_steps)]
    timing = EpisodeTiming()

    def ours_reset() -> TensorDict:
        env.set_seed(seed)
        return env.reset()

    def raw_reset() -> tuple:
        if isinstance(env, GymEnv):
            # GymEnv.set_seed resets the gymnasium env with the seed at once, so its next
            # reset starts the episode after the seeded one: start the same one here.
            raw.reset(seed=seed)
            return raw.reset()
        return raw.reset(seed=seed)

    out, timing.ours_reset = timed(ours_reset)
    (obs, _), timing.raw_reset = timed(raw_reset)
    if not same_obs(out["observation"], obs):
        raise RuntimeError(f"seed {seed}: env.set_seed + reset and raw reset(seed) differ")
    for step, td in enumerate(inputs):
        if step % 2 == 0:
            out, t_ours = timed(lambda td=td: env.step(td))
            (obs, _, term, trunc, _), t_raw = timed(lambda: raw.step(IDLE))
        else:
            (obs, _, term, trunc, _), t_raw = timed(lambda: raw.step(IDLE))
            out, t_ours = timed(lambda td=td: env.step(td))
        timing.ours_steps += t_ours
        timing.raw_steps += t_raw
        timing.steps += 1
        done = bool(out["next", "done"])
        if done != (term or trunc) or not same_obs(out["next", "observation"], obs):
            raise RuntimeError(
                f"seed {seed}, step {step}: {type(env).__name__} and raw gymnasium diverged; the "
                "step throughput ratio would compare different workloads"
            )
        if done:
            break
    return timing


def step_throughput(
    env: EnvBase, raw: gym.Env, seeds: list[int], max_steps: int
) -> tuple[float, float, float, float]:
    """Per-step seconds of both envs over the same episodes, one episode per block.

    Returns:
        Medians over episodes of: ours per step, raw per step (step calls only), then
        ours per step and raw per step with the episode's reset counted in.
    """
    runs = [episode_pair(env, raw, seed, max_steps) for seed in seeds]
    median = statistics.median
    return (
        median(r.ours_steps / r.steps for r in runs),
        median(r.raw_steps / r.steps for r in runs),
        median((r.ours_steps + r.ours_reset) / r.steps for r in runs),
        median((r.raw_steps + r.raw_reset) / r.steps for r in runs),
    )


def wrapper_cpu_per_step(scenario: str, calls: int = 2000) -> float:
    """Seconds per ``HighwayEnv.step`` when the simulator's step returns at once.

    What is left is the wrapper's own work (action conversion, info tensors, output
    tensordict, TorchRL's step bookkeeping): the floor of its cost per step.
    """
    env = HighwayEnv(scenario, seed=0)
    env.reset()
    result = env.gym_env.step(IDLE)
    env.gym_env.step = lambda action: result  # an instance attribute: this env only
    td = TensorDict(action=torch.tensor(IDLE))
    per_call(lambda: env.step(td.clone()), 200)
    seconds = per_call(lambda: env.step(td.clone()), calls)
    env.close()
    return seconds


def envelope_floor(env: HighwayEnv, td: TensorDict) -> Callable[[], None]:
    """``get_state`` + ``reset(set_state)`` with the codec doing no work, as a callable.

    The codec's encode returns a new TensorDict around the leaves of one prebuilt state
    (no simulator read, no copy) and its decode and checks return at once: what is left
    is TorchRL's reset and the state's containers, the part of a snapshot that does not
    depend on the simulator. Each call puts the codec's own methods back when it returns.
    """
    codec = env.codec
    prebuilt = dict(leaves(td["state", "sim"]))
    stubs = {
        "encode": lambda gym_env: nested_tensordict(dict(prebuilt)),
        "decode": lambda gym_env, state: None,
        "check_compatible": lambda state: None,
    }

    def run() -> None:
        vars(codec).update(stubs)  # instance attributes shadow the methods
        try:
            env.get_state()
            env.reset(td, set_state=True)
        finally:
            for name in stubs:
                vars(codec).pop(name)

    return run


def bench(scenario: str, repeats: int, episodes: int) -> None:
    print(f"{scenario}")
    env = HighwayEnv(scenario, seed=0)
    raw = gym.make(scenario, disable_env_checker=True)
    # One warm-up episode per side, then the same episodes for both.
    step_throughput(env, raw, [999], MAX_STEPS)
    seeds = [1000 + i for i in range(max(repeats, episodes))]
    t_ours, t_raw, t_ours_all, t_raw_all = step_throughput(env, raw, seeds, MAX_STEPS)
    ratio = t_raw / t_ours
    print(
        f"  step calls ({len(seeds)} episodes, same seeds and actions on both sides): "
        f"HighwayEnv {1 / t_ours:8.1f}/s, raw gymnasium {1 / t_raw:8.1f}/s"
    )
    claim(f"{scenario}: HighwayEnv / raw step throughput", ratio, ">=0.97")
    t_wrapper = wrapper_cpu_per_step(scenario)
    print(f"  HighwayEnv's own CPU per step, simulator stubbed out: {t_wrapper * 1e6:.0f} us")
    claim(f"{scenario}: HighwayEnv's own CPU per step / raw step", t_wrapper / t_raw)
    # The reference: TorchRL's own gymnasium wrapper, measured the same way, shows what
    # any TorchRL env (tensors in, tensordicts out) costs on top of this simulator.
    torchrl_env = GymEnv(scenario, categorical_action_encoding=True)
    step_throughput(torchrl_env, raw, [999], MAX_STEPS)
    t_gym, t_raw_gym, _, _ = step_throughput(torchrl_env, raw, seeds, MAX_STEPS)
    torchrl_env.close()
    print(
        f"  the same for TorchRL's GymEnv: {1 / t_gym:8.1f}/s, raw gymnasium {1 / t_raw_gym:8.1f}/s"
    )
    claim(f"{scenario}: TorchRL GymEnv / raw step throughput", t_raw_gym / t_gym)
    ratio_all = t_raw_all / t_ours_all
    print(
        f"  for information, resets included: HighwayEnv {1 / t_ours_all:8.1f}/s, "
        f"raw gymnasium {1 / t_raw_all:8.1f}/s, ratio {ratio_all:.4f} (no goal)"
    )
    action = TensorDict(action=torch.tensor(IDLE))

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

    def pickle_round_trip() -> None:
        pickle.loads(pickle.dumps(env.gym_env.unwrapped))

    t_snap, t_copy = interleaved(snapshot_restore, deepcopy, calls=50, repeats=repeats)
    _, t_pickle = interleaved(snapshot_restore, pickle_round_trip, calls=50, repeats=repeats)
    t_codec, _ = interleaved(codec_round_trip, deepcopy, calls=50, repeats=repeats)
    print(
        f"  get_state + reset(set_state) {t_snap * 1e3:.3f} ms, codec encode + decode "
        f"{t_codec * 1e3:.3f} ms, deepcopy {t_copy * 1e3:.3f} ms, pickle dumps + loads "
        f"{t_pickle * 1e3:.3f} ms"
    )
    claim(f"{scenario}: (get_state + restore) / deepcopy", t_snap / t_copy, "<=0.7")
    claim(f"{scenario}: (encode + decode) / deepcopy, codec alone", t_codec / t_copy)
    t_floor, _ = interleaved(envelope_floor(env, td), deepcopy, calls=50, repeats=repeats)
    claim(
        f"{scenario}: (get_state + restore) / deepcopy, codec stubbed out (the floor)",
        t_floor / t_copy,
    )
    claim(f"{scenario}: (get_state + restore) / pickle round trip", t_snap / t_pickle)

    # Where the time goes: SnapshotEnv._reset is the whole restore of ours (checks,
    # decode, output); what env.reset() adds on top is TorchRL's reset bookkeeping.
    def own_restore() -> None:
        env._reset(td, set_state=True)

    def torchrl_restore() -> None:
        env.reset(td, set_state=True)

    t_own, t_reset = interleaved(own_restore, torchrl_restore, calls=50, repeats=repeats)
    t_get, _ = interleaved(env.get_state, deepcopy, calls=50, repeats=repeats)
    print(
        f"  of which get_state {t_get * 1e3:.3f} ms, SnapshotEnv._reset(set_state) "
        f"{t_own * 1e3:.3f} ms, TorchRL's reset bookkeeping {(t_reset - t_own) * 1e3:.3f} ms"
    )
    claim(
        f"{scenario}: (get_state + _reset) / deepcopy, without TorchRL's reset bookkeeping",
        (t_get + t_own) / t_copy,
    )

    def restore() -> None:
        env.reset(td, set_state=True)

    def reset_replay() -> None:
        raw.reset(seed=0)
        for _ in range(5):
            raw.step(IDLE)

    t_restore, t_replay = interleaved(restore, reset_replay, calls=5, repeats=repeats)
    print(f"  restore {t_restore * 1e3:.3f} ms, reset + 5-step replay {t_replay * 1e3:.1f} ms")
    claim(f"{scenario}: restore / (reset + replay of 5 steps)", t_restore / t_replay, "<=1/100")

    state_bytes = sum(t.numel() * t.element_size() for t in state.values(True, True))
    pickled = len(pickle.dumps(env.gym_env.unwrapped))
    print(f"  state {state_bytes} bytes, pickled env {pickled} bytes")
    claim(f"{scenario}: state bytes / pickled env bytes", state_bytes / pickled, "<=1.0")
    env.close()
    raw.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["highway-fast-v0", "merge-v0"])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--episodes",
        type=int,
        default=8,
        help="episodes (blocks) of the step-throughput comparison; at least --repeats",
    )
    args = parser.parse_args()
    for scenario in args.scenarios:
        bench(scenario, args.repeats, args.episodes)


if __name__ == "__main__":
    main()
