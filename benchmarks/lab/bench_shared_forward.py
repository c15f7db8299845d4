"""The drive recipe with one network forward where it ran two or three on the same rows.

``torchrl_grpo.modules.forward_sharing.shared_forward`` runs each of the policy's networks once per
input tensor. ``experiment=drive`` uses it in two places:

* the update: it sums three losses on every minibatch (the clipped surrogate, the
  regression of the enumerated advantages and the crash head's cross-entropy), and each
  ran the policy's network itself;
* the rollout: on every branch step after the first, ``GreedyTail`` ran the network
  for the sampled outputs, then again for the learner's greedy action.

This script measures each way in one process, interleaved so that machine noise hits
all of them:

* the update: ``algo.optimise`` on one batch of the recipe (its replay of 4,096
  groups), forward and backward of every minibatch;
* a rollout step: ``GreedyTail`` on the batch's R x G branch rows at their second step;
* training end to end: ``Trainer.train()`` of ``--frames`` frames on the tensor
  simulator (collection, update and a one-episode evaluation), frames per second, with
  neither, the update's only, or both shared.

"Separate" replaces ``shared_forward`` by a context that does nothing: the network
then runs once per call, as before the change.

Run: ``python benchmarks/lab/bench_shared_forward.py [--frames 150000] [--repeats 2]``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import statistics
import tempfile
import time
import warnings

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from claims import claim
from tensordict import TensorDictBase

import torchrl_grpo.modules.greedy_tail as greedy_tail
import torchrl_grpo.training.algos.base as algo_base
from torchrl_grpo.modules import GreedyTail
from torchrl_grpo.modules.forward_sharing import shared_forward
from torchrl_grpo.training import Trainer, compose_config

#: Training modes: (the update shares, the rollout shares).
MODES = {"separate": (False, False), "update only": (True, False), "shared": (True, True)}


def _separate(policy: object, include_no_grad: bool = False) -> contextlib.nullcontext:
    """A context that does nothing: each call runs the network itself, as before."""
    return contextlib.nullcontext()


def use(update: bool, rollout: bool = False) -> None:
    """Make the update and the rollout policy share the forward (the library's way) or not."""
    algo_base.shared_forward = shared_forward if update else _separate
    greedy_tail.shared_forward = shared_forward if rollout else _separate


def trainer(frames: int, seed: int) -> Trainer:
    """A Trainer of the drive recipe for ``frames`` frames, with no evaluation to speak of."""
    cfg = compose_config(
        [
            "experiment=drive",
            f"experiment.total_frames={frames}",
            f"seed={seed}",
            "experiment.eval_every=0",
            "experiment.final_eval_episodes=1",
            "experiment.baselines=[]",
            "experiment.transfer_gap=false",
            "experiment.progress_bar=false",
            "experiment.checkpoint_every=0",
            "logger=csv",
        ]
    )
    return Trainer(cfg, run_dir=tempfile.mkdtemp(prefix="bench_shared_"))


def branch_rows(algo: object, batch: TensorDictBase) -> TensorDictBase:
    """One branch step of the recipe: its R x G rows, each at the step after its root."""
    cfg = algo.cfg
    n = int(cfg.rollout.groups_per_batch) * int(cfg.algo.group_size)
    rows = batch[:n].select("observation").clone()
    zero = torch.zeros(n, dtype=torch.int64)
    return rows.update(
        {"root_step": zero, "step_count": (zero + 1).unsqueeze(-1), "branch": torch.arange(n)}
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150_000, help="frames of each training run")
    parser.add_argument("--repeats", type=int, default=2, help="training runs of each kind")
    parser.add_argument("--updates", type=int, default=6, help="timed updates of each kind")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    args = parser.parse_args()
    warnings.filterwarnings("ignore")
    logging.disable(logging.WARNING)
    torch.set_num_threads(args.threads)

    # One untimed run first: imports, caches and the first evaluation cost no mode.
    trainer(20_000, seed=args.repeats).train()
    rates: dict[str, list[float]] = {mode: [] for mode in MODES}
    last = None
    for repeat in range(args.repeats):
        for mode in list(MODES)[:: 1 if repeat % 2 == 0 else -1]:
            use(*MODES[mode])
            run = trainer(args.frames, seed=repeat)
            start = time.perf_counter()
            run.train()
            rates[mode].append(run.progress.frames / (time.perf_counter() - start))
            last = run
    assert last is not None
    algo = last.algo
    batch = algo.current_log_probs(algo.replay[:])
    rows = branch_rows(algo, batch)
    recipe = algo.cfg.algo
    rollout = GreedyTail(
        algo.policy,
        int(recipe.explore_steps),
        first_action=str(recipe.first_action),
        tail_policy=algo.tail_policy,
        learner_steps=int(recipe.tail_learner_steps),
    )
    seconds: dict[bool, list[float]] = {True: [], False: []}
    step: dict[bool, list[float]] = {True: [], False: []}
    for update in range(args.updates):
        for shared in (False, True) if update % 2 == 0 else (True, False):
            use(shared, shared)
            start = time.perf_counter()
            stats = algo.optimise(batch)
            seconds[shared].append(time.perf_counter() - start)
            with torch.no_grad():
                start = time.perf_counter()
                for _ in range(10):
                    rollout(rows.clone(False))
                step[shared].append((time.perf_counter() - start) / 10)
    use(True, True)
    update = {k: statistics.median(v) for k, v in seconds.items()}
    branch = {k: statistics.median(v) for k, v in step.items()}
    train = {k: statistics.median(v) for k, v in rates.items()}
    minibatches = int(stats["train/minibatches"])
    print(f"torch threads {torch.get_num_threads()}; update: {batch.shape[0]} rows, ", end="")
    print(f"{minibatches} batches; rollout step: {rows.shape[0]} rows")
    print(f"update          separate {update[False]:7.3f} s   shared {update[True]:7.3f} s")
    print(f"rollout step    separate {branch[False]:7.4f} s   shared {branch[True]:7.4f} s")
    print("training        " + "   ".join(f"{m} {train[m]:,.0f} f/s" for m in MODES))
    claim(
        "experiment=drive: update seconds, separate / shared forward",
        update[False] / update[True],
        note=f"{update[False]:.2f} s vs {update[True]:.2f} s",
    )
    claim(
        "experiment=drive: branch step of the rollout policy, separate / shared forward",
        branch[False] / branch[True],
        note=f"{1e3 * branch[False]:.1f} ms vs {1e3 * branch[True]:.1f} ms, {rows.shape[0]} rows",
    )
    for mode in ("update only", "shared"):
        claim(
            f"experiment=drive: training frames/s, {mode} / separate forward",
            train[mode] / train["separate"],
            note=f"{train[mode]:,.0f}/s vs {train['separate']:,.0f}/s, {args.frames:,} frames",
        )


if __name__ == "__main__":
    main()
