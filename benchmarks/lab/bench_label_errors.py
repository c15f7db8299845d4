"""Do the search's labels see a student's crashes coming, and does its crash head?

A search student (``algo=search_distill``) fits the lookahead search over a run: every
action of a state tried, then the run's greedy actions (H = 8). Where the student still
crashes, either its labels saw nothing (the search over the run would crash there too)
or they flagged the action it took, its branch crashing where another's did not, and
the student did not learn it. This benchmark drives ``--checkpoint``'s greedy policy
through ``--episodes`` episodes on the tensor simulator (highway-env's starting worlds
of seeds ``--seed``.., as ``bench_crash_rates.py``), labels every decision with the
search over ``--searched`` (the run the student fitted: its ``algo.teachers[0]``), and
prints:

* over all decisions: the share of states where some action crashes and another does
  not, the share of those where the student's action is flagged, and the crash head's
  probability for the actions the labels flag and for the safe ones;
* over each crash: whether a decision among the last ``--look-back`` was flagged, and
  the head's probability for the flagged action (``--sequences``: every decision);
* with ``--other`` (another run of the same command, say), where that network's own
  greedy action is flagged at the same decisions, and where both are: whether the two
  networks err in the same states.

    python benchmarks/lab/bench_label_errors.py --checkpoint runs/search_student_round2/last.pt \\
        --searched runs/search_student_round2/teachers/0/last.pt --episodes 1000 --seed 500000
"""

from __future__ import annotations

import argparse
import logging

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from bench_crash_rates import ACTIONS, last_decisions, trained
from tensordict import TensorDictBase, cat

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import CrashHead
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training.algos.search_distill import search_labels
from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.transfer import tensor_episodes

logging.basicConfig(level=logging.INFO, format="%(message)s")

#: States labelled per batched search (5 branch worlds each): bounds the memory.
CHUNK = 8192


def flagged(crashed: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The decisions the labels call errors: the action's branch crashes, another's does not.

    Args:
        crashed: ``[N, n_actions]`` each action's branch crashed.
        action: ``[N]`` the actions taken.

    Example:
        >>> crashed = torch.tensor([[True, False], [True, True], [False, True]])
        >>> flagged(crashed, torch.tensor([0, 0, 0])).tolist()
        [True, False, False]
    """
    return crashed.gather(-1, action.long().unsqueeze(-1)).squeeze(-1) & ~crashed.all(-1)


def labelled(env_cfg, searched: torch.nn.Module, states: TensorDictBase, horizon: int):
    """``search_labels`` of ``states`` by the search over ``searched``, a chunk at a time."""
    parts = []
    for start in range(0, states.shape[0], CHUNK):
        rows = states[start : start + CHUNK]
        sim = TensorHighwayEnv(
            str(env_cfg.scenario), env_overrides(env_cfg), num_envs=5 * rows.shape[0], seed=0
        )
        planner = LookaheadPolicy(sim, DeterministicActor(searched), horizon)
        parts.append(search_labels(planner, rows))
    return cat(parts)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="the student, whose greedy policy drives")
    p.add_argument("--searched", required=True, help="the run whose search labelled it")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=30_000, help="first episode's seed")
    p.add_argument("--horizon", type=int, default=8, help="the search's steps per branch")
    p.add_argument("--look-back", type=int, default=8, help="decisions scored per crash")
    p.add_argument("--sequences", action="store_true", help="print each crash's decisions")
    p.add_argument("--other", default=None, help="a network whose choices are flagged beside")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    env_cfg, student = trained(args.checkpoint)
    searched = trained(args.searched)[1]
    heads = [m for m in student.modules() if isinstance(m, CrashHead)]
    if not heads:
        raise SystemExit(f"{args.checkpoint} has no crash head (model.crash_head=false)")
    greedy = DeterministicActor(student)
    data, steps = tensor_episodes(
        env_cfg, greedy, episodes=args.episodes, seed=args.seed, return_state=True
    )
    states = data[steps]
    labels = labelled(env_cfg, searched, states, args.horizon)
    with torch.no_grad():
        crash_prob = torch.sigmoid(heads[0].crash_logits(states.get("observation")))
    crashed, action = labels.get("search_crashed"), states.get("action").reshape(-1)
    errors = flagged(crashed, action)
    mixed = crashed.any(-1) & ~crashed.all(-1)
    chosen = crash_prob.gather(-1, action.unsqueeze(-1)).squeeze(-1)

    print(
        f"{args.checkpoint} driving {args.episodes} episodes from seeds {args.seed}.., "
        f"labelled by the search (H = {args.horizon}) over {args.searched}"
    )
    print(
        "| decisions | states where some action crashes, another not | student's action "
        "flagged | head's p, their crashing actions: mean (share < 0.1) | their safe ones |"
    )
    print("|---|---|---|---|---|")
    danger, safe = crash_prob[mixed][crashed[mixed]], crash_prob[mixed][~crashed[mixed]]
    print(
        f"| {states.shape[0]} | {int(mixed.sum())} ({100 * float(mixed.float().mean()):.1f}%) | "
        f"{int(errors.sum())} ({100 * float(errors.sum()) / max(int(mixed.sum()), 1):.2f}%) | "
        f"{float(danger.mean()):.3f} ({float((danger < 0.1).float().mean()):.3f}) | "
        f"{float(safe.mean()):.3f} |"
    )

    if args.other is not None:
        with torch.no_grad():
            acted = DeterministicActor(trained(args.other)[1])(states.select("observation").clone())
        theirs = flagged(crashed, acted.get("action").reshape(-1))
        print(
            f"\n{args.other}'s greedy action at the same decisions: flagged at "
            f"{int(theirs.sum())}; at {int((theirs & errors).sum())} of the "
            f"{int(errors.sum())} where the student's is"
        )

    crashes = last_decisions(
        steps, data.get(("next", "crashed")).reshape(steps.shape), args.look_back
    )
    seen, probs = 0, []
    for rows in crashes:
        hit = [j for j in rows if errors[j]]
        seen += bool(hit)
        probs += [float(chosen[hit[0]])] if hit else []
        if args.sequences:
            print(f"a crash at decision {rows[-1]}:")
            for j in rows:
                print(
                    f"  {ACTIONS[int(action[j])]:<10} labels crash: "
                    f"{crashed[j].int().tolist()}  head: "
                    + " ".join(f"{x:.2f}" for x in crash_prob[j].tolist())
                    + ("  <- flagged" if errors[j] else "")
                )
    print(
        f"\n{len(crashes)} crashes; {seen} follow a flagged decision among the last "
        f"{args.look_back}; the head's p for the first flagged action of each: "
        + ", ".join(f"{x:.3f}" for x in sorted(probs))
    )


if __name__ == "__main__":
    main()
