"""A run's greedy policy barred by other runs' crash heads too: do independent heads err apart?

``bench_crash_causes.py`` traces every crash a roundabout-v0 run with a margin still has
to an action its own crash head rated safe, wrongly. If the heads of independently
trained runs err on different states, barring with all of them removes those crashes;
if they err on the same ones, it does not. This script drives the first checkpoint's
greedy policy (its own head and margin) and, in further rows, also bars every action
that any other listed run's head finds more than the margin likelier to crash than
SLOWER. The episodes are the tensor simulator's in float64 from highway-env's starts,
paired against always-SLOWER on them:

    python benchmarks/lab/bench_barring_heads.py --checkpoints <run 0>/last.pt \\
        <run 1>/last.pt <run 2>/last.pt --crash-margin 0.001 --episodes 4000 --seed 61000

It uses the frames of every listed run: a measurement of what an ensemble of heads
could do, not a recipe at equal frames.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from bench_scenario_room import TABLE_HEADER, table_row
from omegaconf import OmegaConf
from tensordict import TensorDictBase

import torchrl_grpo.experimental  # noqa: F401  (runs of algo=grpo_lab load too)
from torchrl_grpo.modules import ConstantActionPolicy
from torchrl_grpo.modules.crash_head import CrashHead, acting_greedily
from torchrl_grpo.training import load_run_policy, make_env
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.transfer import evaluate_on_tensor

warnings.filterwarnings("ignore")

SLOWER = 4


class BarredGreedy:
    """The first head's greedy action (its margin applied), barred by the other heads too.

    Args:
        heads: the runs' crash heads, each with its margin over SLOWER
            (:meth:`~torchrl_grpo.modules.CrashHead.set_margin`); ``heads[0]`` gives the
            logits.
    """

    def __init__(self, heads: list[CrashHead]) -> None:
        self.heads = heads

    @torch.no_grad()
    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get("observation").float()
        with acting_greedily():
            logits = self.heads[0](obs)
        for head in self.heads[1:]:
            logits = torch.where(head.allowed(obs), logits, float("-inf"))  # SLOWER always
        return tensordict.set("action", logits.argmax(-1))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoints", nargs="+", required=True, help="runs with crash heads")
    p.add_argument("--crash-margin", type=float, required=True)
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=61000)
    args = p.parse_args()
    env_cfg = OmegaConf.create(load_checkpoint(args.checkpoints[0])["config"])["env"]
    env = make_env(env_cfg, seed=0)
    heads = []
    for path in args.checkpoints:
        head = next(
            m for m in load_run_policy(path, env_cfg, env).modules() if isinstance(m, CrashHead)
        )
        head.set_margin(args.crash_margin, SLOWER)
        heads.append(head)
    names = [Path(path).parent.name for path in args.checkpoints]

    def play(policy, name: str):  # noqa: ANN001, ANN202
        start = time.perf_counter()
        res = evaluate_on_tensor(
            env_cfg, policy, episodes=args.episodes, seed=args.seed, name=name,
            dtype=torch.float64,
        )  # fmt: skip
        return res, time.perf_counter() - start

    rows = [play(ConstantActionPolicy("SLOWER"), "always-SLOWER")]
    for k in range(1, len(heads) + 1):
        name = f"{names[0]}, margin {args.crash_margin}, barred by " + " + ".join(names[:k])
        rows.append(play(BarredGreedy(heads[:k]), name))
    slower = rows[0][0]
    print(  # noqa: T201 (the benchmark's output)
        f"{env_cfg.scenario}: {args.episodes} tensor-simulator episodes (float64), "
        f"seeds {args.seed}..\n\n{TABLE_HEADER}\n"
        + "\n".join(table_row(res, slower, seconds) for res, seconds in rows)
    )


if __name__ == "__main__":
    main()
