"""What the search would teach a network, on the states the network itself visits.

    python benchmarks/lab/search_labels.py --checkpoint runs/<name>/last.pt \\
        [--episodes 200] [--horizon 8] [--seed 40000]

The network drives greedily on the tensor simulator, from highway-env's episode starts
of ``--seed, --seed + 1, ...``. At every state it visits, the lookahead planner over the
same network scores each action (its branch return over ``--horizon`` steps, the
network's greedy steps after the first: what ``evaluate.py search_horizon=H`` plays).
It prints how the planner's labels relate to the network's own choice:

- the best set: the actions whose score ties the best one's (to 1e-9), and how often
  it holds more than one action (``best_actions`` then labels the lowest index);
- agreement: the network's action in the best set, and equal to the argmax label;
- regret: best score minus the score of the network's action, as a distribution, and
  how often it exceeds 1 (about the reward a crash forfeits within the horizon);
- the argmax labels' and the network's actions' histograms.

The issue's question is why distilling the planner into the network failed: labels
that pick among tied actions by index are noise the network cannot fit, and a regret
that is large only on a few states makes those states rare in the data.
"""

from __future__ import annotations

import argparse
import warnings

import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.batched_search import highway_starts
from torchrl_grpo.branching.keys import MASK
from torchrl_grpo.branching.lookahead import branch_returns
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import make_env
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.pretrained import load_run_policy

warnings.filterwarnings("ignore")
ACTIONS = ["LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER"]


def branch_outcomes(planner: LookaheadPolicy, td) -> tuple[torch.Tensor, torch.Tensor]:
    """``[N, A]`` branch returns (``planner.returns``) and whether each branch crashed."""
    data = planner.branches(td)
    mask = data.get(MASK)
    crashed = (data.get(("next", "crashed")).reshape(mask.shape) & mask).any(-1)
    return branch_returns(data), crashed


@torch.no_grad()
def visit(
    policy: TensorDictModuleBase,
    scenario: str,
    seeds: list[int],
    horizon: int,
    max_steps: int,
    planner: LookaheadPolicy | None = None,
    config: dict | None = None,
) -> dict[str, torch.Tensor]:
    """Every action's score and crash flag at every state the greedy ``policy`` visits;
    what it saw and did.

    ``planner`` scores the actions (default: the search over ``policy``, ``horizon``
    steps, from the whole state). One with an ``outcomes`` method (the search from
    redrawn copies of ``bench_hidden_search``) gives a branch's crash flag as "crashes in
    more than half of the copies". ``config``: the scenario's config overrides (the
    run's ``env.config``, such as a larger observation).
    """
    n = len(seeds)
    if planner is None:
        branches = TensorHighwayEnv(scenario, config, num_envs=5 * n)
        planner = LookaheadPolicy(branches, policy, horizon)
    env = TensorHighwayEnv(scenario, config, num_envs=n, return_state=True)
    td = highway_starts(env, seeds)
    live = torch.ones(n, dtype=torch.bool)
    scores, crashes, chosen, rewards, observations = [], [], [], [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(max_steps):
            rows = live.nonzero().squeeze(-1)
            if rows.numel() == 0:
                break
            if hasattr(planner, "outcomes"):
                score, share = planner.outcomes(td[rows])
                crash = share > 0.5
            else:
                score, crash = branch_outcomes(planner, td[rows])
            scores.append(score)
            crashes.append(crash)
            observations.append(td.get("observation")[rows])
            action = policy(td.clone())["action"]
            chosen.append(action[rows])
            stepped = env.step(td.set("action", action))
            rewards.append(stepped.get(("next", "reward")).reshape(-1)[rows])
            live &= ~stepped.get(("next", "done")).reshape(-1)
            td = step_mdp(stepped)
    return {
        "scores": torch.cat(scores),
        "crashed": torch.cat(crashes),
        "action": torch.cat(chosen),
        "reward": torch.cat(rewards),
        "observation": torch.cat(observations),
    }


def label_stats(scores: torch.Tensor, action: torch.Tensor) -> dict[str, float]:
    """How the planner's labels relate to the network's actions (see the module doc)."""
    best = scores.max(-1, keepdim=True).values
    best_set = scores >= best - 1e-9
    label = scores.argmax(-1)
    regret = (best.squeeze(-1) - scores.gather(-1, action[:, None]).squeeze(-1)).double()
    stats = {
        "states": float(scores.shape[0]),
        "best set > 1 action": best_set.sum(-1).gt(1).double().mean().item(),
        "mean size of the best set": best_set.sum(-1).double().mean().item(),
        "network's action in the best set": best_set.gather(-1, action[:, None])
        .double()
        .mean()
        .item(),
        "network's action == argmax label": (action == label).double().mean().item(),
        "regret > 0.1": (regret > 0.1).double().mean().item(),
        "regret > 1": (regret > 1).double().mean().item(),
    }
    for q in (0.5, 0.9, 0.99):
        stats[f"regret quantile {q}"] = regret.quantile(q).item()
    tied = best_set.sum(-1) > 1
    for a, name in enumerate(ACTIONS):
        stats[f"argmax label {name}"] = (label == a).double().mean().item()
        stats[f"network {name}"] = (action == a).double().mean().item()
        stats[f"tied label {name}"] = (label[tied] == a).double().mean().item()
    return stats


def report(stats: dict[str, float]) -> None:
    for key, value in stats.items():
        if key.startswith(("argmax label", "network ", "tied label")):
            continue
        print(
            f"{key}: {value:.4f}"
            if "quantile" in key or "size" in key
            else f"{key}: {value:.2%}"
            if key != "states"
            else f"states visited: {int(value)}"
        )
    print("| action | argmax labels | network | labels where the set > 1 |")
    print("|---|---|---|---|")
    for name in ACTIONS:
        print(
            f"| {name} | {stats[f'argmax label {name}']:.1%} | {stats[f'network {name}']:.1%} "
            f"| {stats[f'tied label {name}']:.1%} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--seed", type=int, default=40_000)
    parser.add_argument("--max-steps", type=int, default=40)
    args = parser.parse_args()
    env_cfg = OmegaConf.create(load_checkpoint(args.checkpoint)["config"])["env"]
    env = make_env(env_cfg, seed=0)
    policy = DeterministicActor(load_run_policy(args.checkpoint, env_cfg, env))
    seeds = list(range(args.seed, args.seed + args.episodes))
    data = visit(policy, str(env_cfg.scenario), seeds, args.horizon, args.max_steps)
    report(label_stats(data["scores"], data["action"]))


if __name__ == "__main__":
    main()
