"""The drive recipe's losses with one network forward per minibatch, against one per loss.

``experiment=drive`` sums three losses on every minibatch (the clipped surrogate, the
regression of the enumerated advantages and the crash head's cross-entropy), and each
ran the policy's network itself. ``torchrl_grpo.modules.shared_forward`` runs it once.
This script measures both ways in one process, interleaved so that machine noise hits
both:

* the update: ``algo.optimise`` on one batch of the recipe (its replay of 4,096
  groups), forward and backward of every minibatch;
* training end to end: ``Trainer.train()`` of ``--frames`` frames on the tensor
  simulator (collection, update and a one-episode evaluation), frames per second.

"Separate" replaces ``shared_forward`` by a context that does nothing: the losses then
run the network three times, as before the change.

Run: ``python benchmarks/bench_shared_forward.py [--frames 150000] [--repeats 2]``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import statistics
import tempfile
import time
import warnings

import torch
from claims import claim

import torchrl_grpo.training.algos.base as algo_base
from torchrl_grpo.training import Trainer, compose_config

_SHARED = algo_base.shared_forward


def use(shared: bool) -> None:
    """Make ``Algorithm.optimise`` share the forward (the library's way) or not."""
    # nullcontext(policy) does nothing: each loss runs the network itself, as before.
    algo_base.shared_forward = _SHARED if shared else contextlib.nullcontext


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

    # One untimed run first: imports, caches and the first evaluation cost neither side.
    trainer(20_000, seed=args.repeats).train()
    rates: dict[bool, list[float]] = {True: [], False: []}
    last = None
    for repeat in range(args.repeats):
        for shared in (False, True) if repeat % 2 == 0 else (True, False):
            use(shared)
            run = trainer(args.frames, seed=repeat)
            start = time.perf_counter()
            run.train()
            rates[shared].append(run.progress.frames / (time.perf_counter() - start))
            last = run
    assert last is not None
    algo = last.algo
    batch = algo.current_log_probs(algo.replay[:])
    seconds: dict[bool, list[float]] = {True: [], False: []}
    for update in range(args.updates):
        for shared in (False, True) if update % 2 == 0 else (True, False):
            use(shared)
            start = time.perf_counter()
            stats = algo.optimise(batch)
            seconds[shared].append(time.perf_counter() - start)
    use(True)
    update = {k: statistics.median(v) for k, v in seconds.items()}
    train = {k: statistics.median(v) for k, v in rates.items()}
    rows, minibatches = batch.shape[0], int(stats["train/minibatches"])
    print(f"torch threads {torch.get_num_threads()}; update: {rows} rows, {minibatches} batches")
    print(f"update          separate {update[False]:7.3f} s   shared {update[True]:7.3f} s")
    print(f"training        separate {train[False]:7.0f} f/s shared {train[True]:7.0f} f/s")
    claim(
        "experiment=drive: update seconds, separate / shared forward",
        update[False] / update[True],
        note=f"{update[False]:.2f} s vs {update[True]:.2f} s",
    )
    claim(
        "experiment=drive: training frames/s, shared / separate forward",
        train[True] / train[False],
        note=f"{train[True]:,.0f}/s vs {train[False]:,.0f}/s, {args.frames:,} frames",
    )


if __name__ == "__main__":
    main()
