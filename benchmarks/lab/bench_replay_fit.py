"""How well a trained policy fits the groups it trained on: its choices on its own replay.

A run of ``algo=grpo_branch`` with enumerated first actions, a scripted tail and
``algo.replay_groups`` saves its replay in its checkpoint: the last groups it trained
on, each one root whose every action was scored (``Q_rule(s, a)`` over the rollout
horizon, a crash forfeiting the episode's steps left and paying ``algo.crash_penalty``).
This script takes the checkpoint's greedy policy on those roots and, by the spread of
each root's scores (best minus worst action), prints how often its choice is costly:
``regret >= 0.5`` (a slower action) and ``regret >= 10`` (an action whose branch
crashes). Roots with a spread of 10 or more are the danger states, where an action
crashes; the share of them where the policy picks a crashing action, times the danger
decisions of an episode, is the crash rate that imitation errors alone would give.

    python benchmarks/lab/bench_replay_fit.py --checkpoint outputs/.../last.pt [--checkpoint ...]
"""

from __future__ import annotations

import argparse

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from bench_crash_rates import trained
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.training import load_checkpoint

#: Spread buckets (return units): ties, small differences, larger ones, crashes.
BUCKETS = ((0.0, 0.5), (0.5, 2.0), (2.0, 10.0), (10.0, float("inf")))


def replay_roots(ckpt: dict) -> tuple[TensorDict, torch.Tensor]:
    """The replay's roots (one row each, its first branch's step) and ``Q[root, action]``."""
    if ckpt.get("replay") is None:
        raise ValueError("the checkpoint holds no replay: train with algo.replay_groups")
    storage = ckpt["replay"]["_storage"]
    rows = int(storage["_len"])
    data = TensorDict({k: v[:rows] for k, v in storage["_storage"].items()}, batch_size=[rows])
    group = int(ckpt["config"]["algo"]["group_size"])
    ids = data["group_id"].reshape(-1, group)
    # The replay writes whole groups, so a group's rows are contiguous.
    if not bool((ids == ids[:, :1]).all()):
        raise ValueError("the replay's groups are not contiguous rows")
    action = data["action"].reshape(-1, group)
    advantage = data["advantage"].reshape(-1, group)
    q = torch.full_like(advantage, float("nan")).scatter_(1, action, advantage)
    if bool(q.isnan().any()):
        raise ValueError("a group does not try every action once: use algo.first_action=enumerate")
    return data[::group], q


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", action="append", required=True, help="a run's last.pt")
    args = p.parse_args()
    torch.set_num_threads(1)
    for path in args.checkpoint:
        roots, q = replay_roots(load_checkpoint(path))
        _, policy = trained(path)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            greedy = policy(roots.select("observation").clone())["action"].reshape(-1)
        best = q.max(1).values
        regret = best - q.gather(1, greedy[:, None]).squeeze(1)
        spread = best - q.min(1).values
        print(f"{path}: {len(q)} replayed roots")
        print("| spread of the scores | roots | greedy regret >= 0.5 | greedy regret >= 10 |")
        print("|---|---|---|---|")
        for lo, hi in BUCKETS:
            m = (spread >= lo) & (spread < hi)
            if not bool(m.any()):
                continue
            share = 100 * float(m.float().mean())
            costly = 100 * float((regret[m] >= 0.5).float().mean())
            crash = 100 * float((regret[m] >= 10).float().mean())
            print(f"| [{lo:g}, {hi:g}) | {share:.1f}% | {costly:.1f}% | {crash:.2f}% |")


if __name__ == "__main__":
    main()
