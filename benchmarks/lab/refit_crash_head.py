"""DAgger for a crash head: refit it on the states its own greedy policy visits.

A roundabout-v0 run with a crash head and a margin still crashes in 0.2 to 0.3% of
episodes, and ``bench_crash_causes.py`` traces every one of those crashes to an action
the head rated within the margin of SLOWER where that action, then always-SLOWER,
crashes. Acting on the head selects its errors: the greedy policy takes the risky
actions exactly where the head underrates them, states its training groups (drawn by
the sampling policy) met rarely. This script gives the head those states:

Round k: the run's greedy policy, barred by its (refitted) head at ``--crash-margin``,
drives ``--episodes`` episodes on the tensor simulator in float64 from highway-env's
starts of seeds ``--seed + k * episodes ...`` (disjoint from the selection's 60000..
and the held-out 40000..). From every state it visits, each action is branched and then
followed by always-SLOWER to the episode's end, the head's own labels
(``algo.crash_head_tail``). The states join those of the earlier rounds (DAgger's
aggregation) and the network minimises the crash head's binary cross-entropy on them,
states where the actions' labels disagree weighted by ``--weight``, plus
``--anchor`` times the squared change of its policy logits from the run's: the policy
is the run's, and only what the head bars changes.

Before each fit, the new round's states measure the head as it drove them: the share
of states where the greedy action (margin applied) crashes and SLOWER does not, the
errors a margin cannot remove. After each round the network is saved as
``<out>/round_<k>.pt``, a checkpoint every evaluation reads
(``bench_scenario_room.py --checkpoints``, ``bench_scenarios.py --grpo``).

    python benchmarks/lab/refit_crash_head.py --checkpoint <run>/last.pt --out <dir> \\
        --crash-margin 0.003 [--rounds 3] [--episodes 2000] [--weight 4]

Frames: the driven steps and every branch step, counted as training counts them.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import warnings
from pathlib import Path

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from bench_crash_causes import N_ACTIONS, SLOWER, branch_crashes
from omegaconf import OmegaConf
from search_fit import save_round
from torch.nn import functional as F

import torchrl_grpo.experimental  # noqa: F401  (runs of algo=grpo_lab load too)
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY
from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.training import load_run_policy, make_env
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.model_builder import set_crash_margin
from torchrl_grpo.training.transfer import tensor_episodes

warnings.filterwarnings("ignore")
log = logging.getLogger(__name__)


@torch.no_grad()
def visit(env_cfg, policy, episodes: int, seed: int) -> dict[str, torch.Tensor | int]:
    """The greedy policy's states, each action's crash label there, and the frames used.

    Returns:
        ``observation`` ``[n, ...]`` (float32), ``crashed`` ``[n, 5]`` (action ``a``
        first, then always-SLOWER), ``greedy`` ``[n]`` (the action taken) and ``frames``.
    """
    data, before = tensor_episodes(
        env_cfg, policy, episodes=episodes, seed=seed, return_state=True, dtype=torch.float64
    )
    steps = data[before]
    states = steps.get(STATE_KEY)
    n = states.batch_size[0]
    crashed, branch_steps = branch_crashes(
        env_cfg,
        states.unsqueeze(1).expand(n, N_ACTIONS).reshape(-1),
        torch.arange(N_ACTIONS).repeat(n),
        count_steps=True,
        native=True,
    )
    taken = steps.get("action")
    return {
        "observation": steps.get("observation").float(),
        "crashed": crashed.reshape(n, N_ACTIONS),
        "greedy": taken.argmax(-1) if taken.dim() == 2 else taken,
        "frames": n + branch_steps,
    }


def head_loss(
    head: CrashHead,
    obs: torch.Tensor,
    crashed: torch.Tensor,
    start_logits: torch.Tensor,
    weight: float,
    anchor: float,
    miss_weight: float = 1.0,
) -> torch.Tensor:
    """The crash logits' cross-entropy (disagreeing states weighted) plus the logits' anchor.

    ``miss_weight`` multiplies the terms of the actions that crash where SLOWER does not
    and that the head's margin allows: the errors that the greedy policy acts on.
    """
    logits, crash = head._split(obs)
    deciding = crashed.any(-1) & ~crashed.all(-1)
    per_action = F.binary_cross_entropy_with_logits(
        crash, crashed.to(crash.dtype), reduction="none"
    )
    if miss_weight != 1.0 and head.margin is not None:
        missed = head._allowed(crash) & crashed & ~crashed[:, [head.fallback]]
        per_action = torch.where(missed, miss_weight * per_action, per_action)
    scale = torch.where(deciding, weight, 1.0)
    drift = (logits - start_logits).pow(2).sum(-1)
    return (scale * per_action.sum(-1) + anchor * drift).mean()


def fit(head: CrashHead, data: dict[str, torch.Tensor], start: torch.Tensor, args) -> float:  # noqa: ANN001
    """Adam over ``data``; the last epoch's mean loss."""
    optim = torch.optim.Adam(head.net.parameters(), lr=args.lr)
    n, last = data["observation"].shape[0], 0.0
    for _ in range(args.epochs):
        total = 0.0
        for idx in torch.randperm(n).split(1024):
            loss = head_loss(
                head, data["observation"][idx], data["crashed"][idx], start[idx],
                args.weight, args.anchor, args.miss_weight,
            )  # fmt: skip
            optim.zero_grad()
            loss.backward()
            optim.step()
            total += loss.item() * len(idx)
        last = total / n
    return last


def wrong_greedy(crashed: torch.Tensor, greedy: torch.Tensor) -> float:
    """Share of states where the action taken crashes and SLOWER does not."""
    taken = crashed.gather(1, greedy.reshape(-1, 1)).squeeze(1)
    return float((taken & ~crashed[:, SLOWER]).double().mean())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a run's last.pt, with a crash head")
    p.add_argument("--out", required=True)
    p.add_argument("--crash-margin", type=float, required=True)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--episodes", type=int, default=2000, help="driven episodes a round")
    p.add_argument("--seed", type=int, default=200_000, help="the rounds' first start")
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--weight", type=float, default=4.0, help="states the labels disagree on")
    p.add_argument("--anchor", type=float, default=1.0, help="the policy logits' pull back")
    p.add_argument(
        "--miss-weight", type=float, default=1.0,
        help="actions the margin allows that crash where SLOWER does not",
    )  # fmt: skip
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = load_checkpoint(args.checkpoint)
    env_cfg = OmegaConf.create(ckpt["config"])["env"]
    policy = load_run_policy(args.checkpoint, env_cfg, make_env(env_cfg, seed=0))
    set_crash_margin(policy, args.crash_margin)
    head = next(m for m in policy.modules() if isinstance(m, CrashHead))
    run_logits = copy.deepcopy(head)
    data: dict[str, list[torch.Tensor]] = {"observation": [], "crashed": []}
    history, frames = [], 0
    for k in range(args.rounds):
        seed = args.seed + k * args.episodes
        visited = visit(env_cfg, policy, args.episodes, seed)
        frames += int(visited["frames"])
        crashed = visited["crashed"]
        row = {
            "round": k + 1,
            "states": int(crashed.shape[0]),
            "greedy_wrong": wrong_greedy(crashed, visited["greedy"]),
            "deciding": float((crashed.any(-1) & ~crashed.all(-1)).double().mean()),
        }
        with torch.no_grad():
            allowed = head.allowed(visited["observation"])
        row["allowed_wrong"] = float(
            (allowed & crashed & ~crashed[:, [SLOWER]]).any(-1).double().mean()
        )
        for key in data:
            data[key].append(visited[key])
        merged = {key: torch.cat(value) for key, value in data.items()}
        with torch.no_grad():
            start = run_logits._split(merged["observation"])[0]
        row["loss"] = fit(head, merged, start, args)
        row["frames"] = frames
        log.info(json.dumps(row))
        history.append(row)
        save_round(ckpt, policy, out, k + 1, history)


if __name__ == "__main__":
    main()
