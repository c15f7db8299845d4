"""HighJax 0.1.0 stepped like highway-fast-v0, timed on request: bench_tensor_env's peer.

HighJax needs jax (and declares Python >= 3.14), so it usually lives in a venv of its
own (docs/benchmarks.md, "Peers"). ``bench_tensor_env.py --highjax-python PYTHON`` starts
this script with that venv's python, once per batch size, and drives it over a line
protocol, so that its blocks interleave with the torch and EnvPool blocks of the same run:

* it prints ``ready`` once the step is compiled and warmed up;
* each ``CALLS`` line read on stdin steps ``CALLS`` times and answers the env-steps/s;
* end of input ends it.

The env is configured like highway-fast-v0: 3 lanes, 20 other vehicles, 5 substeps of
0.2 s per 1 s step, 30 s episodes; B worlds stepped by ``jit(vmap(env.step))``, whose
``step`` resets finished worlds itself (as EnvPool does, and as ``step_and_maybe_reset``
does for TensorHighwayEnv). Actions are always IDLE (1).

Run by hand: ``echo 20 | /work/venv-jax/bin/python benchmarks/highjax_worker.py --batch 1024``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, required=True)
    parser.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    args = parser.parse_args()
    # XLA's CPU thread pool: as many threads as the cores torch and EnvPool get.
    os.environ.setdefault(
        "XLA_FLAGS",
        f"--xla_cpu_multi_thread_eigen={'true' if args.threads > 1 else 'false'} "
        f"intra_op_parallelism_threads={args.threads}",
    )
    import highjax
    import jax
    import jax.numpy as jnp

    env, params = highjax.make("highjax-highway-v0", n_lanes=3, n_npcs=20)
    env.n_sub_ts_per_t = 5  # highway-fast-v0: policy_frequency 1, simulation_frequency 5
    params = params.replace(seconds_per_sub_t=0.2, duration=30.0)
    batch = args.batch
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    action = jnp.full((batch,), 1, dtype=jnp.int32)

    @jax.jit
    def step(keys, state):
        keys, step_keys = jax.vmap(lambda k: tuple(jax.random.split(k)))(keys)
        obs, state, reward, done, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            step_keys, state, action, params
        )
        return keys, state, obs, reward, done

    out = step(keys, state)
    jax.block_until_ready(out)
    keys, state = out[0], out[1]
    print("ready", flush=True)
    for line in sys.stdin:
        calls = int(line)
        start = time.perf_counter()
        for _ in range(calls):
            keys, state, obs, reward, done = step(keys, state)
        jax.block_until_ready(obs)
        print(calls * batch / (time.perf_counter() - start), flush=True)


if __name__ == "__main__":
    main()
