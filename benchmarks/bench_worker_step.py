"""What a branch worker adds to a highway-env step, measured in one process on the same scenes.

A worker that runs whole branches (``BranchRunner``) restores each branch's state,
then every step builds the policy's input, runs its copy of the policy, checks the
action and steps TorchRL's env. This script takes the same branches (roots from
``reset_roots``, scripted actions) four ways, interleaved round by round, and prints
the median CPU ms per step of each:

- ``gym``: the gymnasium env inside the worker env, stepped directly (restores untimed),
  with the worker env's Kinematics observation (``FastKinematicObservation``);
- ``torchrl``: the worker env's TorchRL ``step`` (restores untimed);
- ``runner-scripted``: ``BranchRunner`` with a scripted policy (restores, policy input,
  action check, rows: everything but a real policy);
- ``runner-mlp``: ``BranchRunner`` with the MLP actor of ``bench_ceiling.py``, whose
  sampled action is then replaced by the scripted one (same scenes, the actor's cost);
- ``actor-modules`` and ``actor-direct``: ``BranchRunner`` with that actor acting,
  through its TensorDict modules, and through its direct path (``direct_actor``: the
  default). Both draw the same samples, so they drive the same scenes.

Then it times the parts of ``runner-mlp`` (wall ms per step, one pass): the policy, the
action check, the restores, TorchRL's step, and the rest (the policy's input, rows).

Run: ``python benchmarks/bench_worker_step.py [--scenarios merge-v0] [--repeats 5]``.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import torch
from bench_ceiling import make_policy
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType

import torchrl_grpo.branching.branch_runner as runner_module
from torchrl_grpo.branching import reset_roots
from torchrl_grpo.branching.branch_runner import BranchRunner, RolloutSetup
from torchrl_grpo.branching.pipe_arrays import STATE_NEVER, to_arrays
from torchrl_grpo.branching.policy_transport import pack_policy
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.envs.highway.fast_observation import use_fast_kinematics

warnings.filterwarnings("ignore", message=".*is out of date.*")
clock = time.process_time


class Scripted(torch.nn.Module):
    """Plays ``table[branch, t]``, after running ``inner`` (if any) for its cost."""

    def __init__(self, table: torch.Tensor, inner: torch.nn.Module | None = None) -> None:
        super().__init__()
        self.table, self.inner = table, inner

    def forward(self, td):
        if self.inner is not None:
            td = self.inner(td)
        t = int(td["step_count"][0, 0] - td["root_step"][0])
        td["action"] = self.table[int(td["branch"][0]), t].reshape(1)
        return td


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=["highway-fast-v0", "merge-v0"])
    parser.add_argument("--branches", type=int, default=16)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5, help="interleaved rounds")
    args = parser.parse_args()
    torch.set_num_threads(1)
    n, h = args.branches, args.horizon
    for scenario in args.scenarios:
        plain = HighwayEnv(scenario, seed=0)
        env = HighwayEnv(scenario, return_state=True)
        roots = reset_roots(plain, n, seed=1)["state"]
        table = torch.randint(5, (n, h), generator=torch.Generator().manual_seed(0))
        obs = [k for k in env.observation_spec.keys(True, True) if _as_tuple(k)[0] != "state"]
        keys = [*obs, *env.done_keys]

        def runner(policy, keys=keys, env=env):
            run = BranchRunner(env)
            setup = RolloutSetup(
                pack_policy(policy),
                keys,
                [*keys, *env.reward_keys],
                STATE_NEVER,
                h,
                ExplorationType.RANDOM,
            )
            run(("setup", setup))
            return run

        scripted, mlp = runner(Scripted(table)), runner(Scripted(table, make_policy(plain)))
        actor_direct, actor_modules = runner(make_policy(plain)), runner(make_policy(plain))
        actor_modules.policy.call = actor_modules.policy.policy  # the direct path off
        states = [to_arrays(roots[b]) for b in range(n)]

        def direct(torchrl: bool, env=env, roots=roots, table=table) -> tuple[float, int]:
            spent, steps = 0.0, 0
            env.return_state = False  # as a worker steps when it keeps no state
            for b in range(n):
                env.reset(TensorDict(state=roots[b]), set_state=True)
                # The gym step observes as the worker env's own steps do (no pandas).
                use_fast_kinematics(env.gym_env.unwrapped)
                for t in range(h):
                    start = clock()
                    if torchrl:
                        done = bool(env.step(TensorDict(action=table[b, t]))["next", "done"])
                    else:
                        out = env.gym_env.step(int(table[b, t]))
                        done = out[2] or out[3]
                    spent += clock() - start
                    steps += 1
                    if done:
                        break
            env.return_state = True
            return spent, steps

        def branches(run, states=states) -> tuple[float, int]:
            start, steps = clock(), 0
            for b in range(n):
                steps += run(("branch", b, states[b], (0, b, 0)))[1]["length"]
            return clock() - start, steps

        ways = {
            "gym": lambda: direct(False),
            "torchrl": lambda: direct(True),
            "runner-scripted": lambda run=scripted: branches(run),
            "runner-mlp": lambda run=mlp: branches(run),
            "actor-modules": lambda run=actor_modules: branches(run),
            "actor-direct": lambda run=actor_direct: branches(run),
        }
        times: dict[str, list[float]] = {k: [] for k in ways}
        for _ in range(args.repeats):
            for name, way in ways.items():
                spent, steps = way()
                times[name].append(1e3 * spent / steps)
        print(f"{scenario}: CPU ms per step, medians of {args.repeats} rounds (ranges)")
        for name, values in times.items():
            print(
                f"  {name:<16} {statistics.median(values):6.2f} "
                f"({min(values):.2f}-{max(values):.2f})"
            )
        parts = time_parts(mlp, env, lambda run=mlp: branches(run))
        print(
            "  parts of runner-mlp, wall ms per step: "
            + ", ".join(f"{k} {v:.2f}" for k, v in parts.items())
        )


def time_parts(run: BranchRunner, env: HighwayEnv, go) -> dict[str, float]:
    """Wall ms per step of the parts of ``go()`` (branches on ``run``), one pass."""
    spent = dict.fromkeys(("policy", "check", "restore", "step"), 0.0)

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - start

        return wrapper

    module = runner_module
    saved = (run.policy.call, module.check_policy_actions, module.step_keeping_state)
    run.policy.call = timed("policy", run.policy.call)
    runner_module.check_policy_actions = timed("check", saved[1])
    runner_module.step_keeping_state = timed("step", saved[2])
    env.reset = timed("restore", env.reset)
    try:
        start = time.perf_counter()
        _, steps = go()
        total = time.perf_counter() - start
    finally:
        run.policy.call = saved[0]
        runner_module.check_policy_actions, runner_module.step_keeping_state = saved[1:]
        del env.reset
    out = {k: 1e3 * v / steps for k, v in spent.items()}
    out["rest"] = 1e3 * total / steps - sum(out.values())
    return out


def _as_tuple(key) -> tuple:
    return key if isinstance(key, tuple) else (key,)


if __name__ == "__main__":
    main()
