"""Record highway-env's own statistics, once, for the tensor simulator's fresh-reset parity test.

For each scenario it runs highway-env (through :class:`~torchrl_grpo.envs.HighwayEnv`)
for ``--episodes`` episodes of each policy (always-IDLE, always-SLOWER, random, the
rule policy), episode ``k`` reset with seed ``k``, and writes per-episode returns,
crash flags and lengths, plus the initial worlds' statistics (gaps between
consecutive vehicles, the other vehicles' speeds, every vehicle's lane) to
``tests/data/highway_reference/<scenario>.json``. The parity tests and
``benchmarks/bench_parity.py`` compare the tensor simulator against these files
without running highway-env again.

    python scripts/highway_reference.py --scenario highway-fast-v0 --episodes 1000
    python scripts/highway_reference.py --scenario highway-v0 --episodes 200 --workers 2
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.envs.highway.lane_constants import lane_keys
from torchrl_grpo.envs.highway.parity_policies import ladder_policies

OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "highway_reference"


def initial_world(env: HighwayEnv) -> dict[str, list]:
    """Gaps between consecutive vehicles (road order), others' speeds, lanes.

    A lane is its id within its road (``lane_index[2]``), on intersection-v0 (one lane
    a road) its place in the network's lane order.
    """
    core = env.gym_env.unwrapped
    vehicles = core.road.vehicles
    xs = [float(v.position[0]) for v in vehicles]
    keys = lane_keys(core.road.network)
    flat = env.scenario == "intersection-v0"
    return {
        "gaps": [round(b - a, 6) for a, b in zip(xs, xs[1:], strict=False)],
        "speeds": [round(float(v.speed), 6) for v in vehicles if v is not core.vehicle],
        "lanes": [keys.index(v.lane_index) if flat else int(v.lane_index[2]) for v in vehicles],
    }


def run(job: tuple[str, str, list[int]]) -> dict:
    """Episodes of one policy on seeds ``seeds``."""
    scenario, name, seeds = job
    torch.set_num_threads(1)
    env = HighwayEnv(scenario)
    policy = ladder_policies(scenario, env.config, seed=0)[name]
    out: dict = {"returns": [], "crashed": [], "lengths": [], "initial": []}
    for seed in seeds:
        env.set_seed(seed)
        td = env.reset()
        if name == "idle":
            out["initial"].append(initial_world(env))
        total, steps = 0.0, 0
        while True:
            td = policy(td)
            td = env.step(td)
            total += float(td["next", "reward"])
            steps += 1
            if bool(td["next", "done"]):
                break
            td = TensorDict({k: td["next", k] for k in ("observation",)}, batch_size=[])
        out["returns"].append(round(total, 9))
        out["crashed"].append(bool(td["next", "crashed"]))
        out["lengths"].append(steps)
    return out


def main() -> None:
    """Run every policy's episodes in ``--workers`` processes and write the reference."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="highway-fast-v0")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    seeds = list(range(args.episodes))
    chunks = [seeds[i :: args.workers] for i in range(args.workers)]
    names = [n for n in ladder_policies(args.scenario, {}) if n != "drive"]
    jobs = [(args.scenario, name, chunk) for name in names for chunk in chunks]
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        results = pool.map(run, jobs)
    data: dict = {"scenario": args.scenario, "episodes": args.episodes, "policies": {}}
    for (_, name, chunk), res in zip(jobs, results, strict=True):
        merged = data["policies"].setdefault(
            name, {"seeds": [], "returns": [], "crashed": [], "lengths": []}
        )
        merged["seeds"] += chunk
        for key in ("returns", "crashed", "lengths"):
            merged[key] += res[key]
        if name == "idle":
            data.setdefault("initial", []).extend(res["initial"])
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"{args.scenario}.json"
    path.write_text(json.dumps(data, separators=(",", ":")))
    print(f"wrote {path} in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
