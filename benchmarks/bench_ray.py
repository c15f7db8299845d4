"""Branch groups per second on Ray against the local collector, and a K-node projection.

Measures in one run, on this machine, with the training config's policy network and
rollout shape (highway-fast-v0, G=8, H=8, R=8, trunk decision points every K=4 steps):

- ``local``: the trainer's local collector, ``GroupCollector`` over a
  ``BranchParallelEnv`` of ``--workers`` worker processes;
- ``ray``: ``RayGroupCollector`` with ``--actors`` actors, each one in-process env
  (``workers_per_actor=1``, ``env_backend=single``), same total groups per batch;
- ``update``: the learner's update on one such batch (``Trainer._update``: advantage,
  ``algo.epochs`` passes of minibatches through ``GRPOLoss`` and Adam).

Both collectors do the same work per batch: trunk steps to reach the decision points,
then R groups. The first batch of each (actor start, imports, the first trunks) is
not timed. The two are measured in alternation, ``--repeats`` times, so that load from
other processes hits both alike. It prints groups/s of each, the ratio ray / local
(the engine's overhead on one machine), and the projection of training throughput on
K nodes (see docs/distributed.md):

    iteration(K) = R / (K * rate_node) + update    (synchronous: collect, then update)
    groups/s(K)  = R / iteration(K)

Run: ``python benchmarks/bench_ray.py [--batches 3] [--repeats 2] [--actors 2]``
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import statistics
import time
import warnings
from pathlib import Path

import torch
from claims import claim
from hydra import compose, initialize_config_dir

from torchrl_grpo.branching import GroupCollector, make_branch_env
from torchrl_grpo.distributed import RayGroupCollector, init_ray
from torchrl_grpo.training import Trainer, register_configs
from torchrl_grpo.training.trainer import PhaseTimer

warnings.filterwarnings("ignore")
logging.basicConfig(level=logging.WARNING)

p = argparse.ArgumentParser()
p.add_argument("--scenario", default="highway-fast-v0")
p.add_argument("--group-size", type=int, default=8)
p.add_argument("--horizon", type=int, default=8)
p.add_argument("--groups", type=int, default=8, help="R, groups per batch")
p.add_argument("--batches", type=int, default=3, help="timed batches per measurement")
p.add_argument("--repeats", type=int, default=2)
p.add_argument("--workers", type=int, default=2, help="local ParallelEnv workers")
p.add_argument("--actors", type=int, default=2, help="Ray actors")
args = p.parse_args()

torch.set_num_threads(1)  # as the actors do: the env workers need the cores
conf = Path(__file__).resolve().parents[1] / "conf"
register_configs()
with initialize_config_dir(str(conf), version_base=None):
    cfg = compose(
        "config",
        [
            "logger=none",
            f"env.scenario={args.scenario}",
            f"algo.group_size={args.group_size}",
            f"rollout.horizon={args.horizon}",
            f"rollout.groups_per_batch={args.groups}",
        ],
    )
run_dir = Path("/tmp/bench_ray")
trainer = Trainer(cfg, run_dir=run_dir)
policy = trainer.policy
common = dict(
    group_size=args.group_size,
    horizon=args.horizon,
    groups_per_batch=args.groups,
    roots="trunk",
    decision_interval=int(cfg.rollout.decision_interval),
    seed=0,
)


def timed(collector, batches: int) -> tuple[float, object]:
    """Groups per second over ``batches`` batches, after one untimed warm-up batch."""
    it = iter(collector)
    batch = next(it)
    start = time.perf_counter()
    for _ in range(batches):
        batch = next(it)
    elapsed = time.perf_counter() - start
    return batches * args.groups / elapsed, batch


def local_rate() -> tuple[float, object]:
    env = make_branch_env(args.scenario, args.workers, mp_start_method="fork")
    with GroupCollector(env, policy, **common) as collector:
        return timed(collector, args.batches)


def ray_rate() -> float:
    factory = functools.partial(make_branch_env, args.scenario, 1, backend="single")
    cpus = (os.cpu_count() or 1) / args.actors
    with RayGroupCollector(
        factory, policy, num_actors=args.actors, num_cpus_per_actor=cpus, **common
    ) as collector:
        return timed(collector, args.batches)[0]


init_ray(object_store_memory=256 * 1024**2)
rates: dict[str, list[float]] = {"local": [], "ray": [], "update": []}
batch = None
for _ in range(args.repeats):
    rate, batch = local_rate()
    rates["local"].append(rate)
    rates["ray"].append(ray_rate())
    start = time.perf_counter()
    trainer.algo.update(batch.clone(), PhaseTimer())
    rates["update"].append(time.perf_counter() - start)

local = statistics.median(rates["local"])
ray_groups = statistics.median(rates["ray"])
update = statistics.median(rates["update"])
load = os.getloadavg()[0]
print(
    f"{args.scenario}, G={args.group_size}, H={args.horizon}, R={args.groups}, trunk roots K="
    f"{cfg.rollout.decision_interval}; {os.cpu_count()} cores, load average {load:.1f}"
)
print(f"local GroupCollector, ParallelEnv W={args.workers}: {local:.2f} groups/s  {rates['local']}")
print(f"Ray, {args.actors} actors x 1 env:           {ray_groups:.2f} groups/s  {rates['ray']}")
claim(
    f"{args.scenario}: groups/s, Ray ({args.actors} actors) / local ParallelEnv", ray_groups / local
)
print(f"learner update per batch of {args.groups} groups: {update:.2f} s  {rates['update']}")
print("projection, synchronous (node = this machine's Ray rate):")
print("  K nodes | collect s | update s | groups/s | speedup vs 1 node")
base = args.groups / (args.groups / ray_groups + update)
for k in (1, 2, 4, 8, 16, 32):
    collect = args.groups / (k * ray_groups)
    total = args.groups / (collect + update)
    print(f"  {k:7d} | {collect:9.2f} | {update:8.2f} | {total:8.2f} | {total / base:5.2f}")
print(f"  limit (update only): {args.groups / update:.2f} groups/s")
