"""Expert iteration from the lookahead planner: a network fits its own search, round by round.

    python benchmarks/lab/search_fit.py --checkpoint runs/<name>/last.pt --out runs/search_fit \\
        [--rounds 3] [--episodes 200] [--horizon 8] [--eval-episodes 1000]
    python benchmarks/lab/search_fit.py --checkpoint runs/best/last.pt --out runs/crash_fit \
        --loss crash --weight 8 --lr 2e-4 --rounds 6 --episodes 600   # docs/lab/targets.md

Round k: the network drives ``--episodes`` episodes greedily on the tensor simulator
(highway-env's starts of seeds ``40000 + k * episodes ...``, disjoint between rounds),
and the planner over the same network scores every action at each state it visits
(``search_labels.visit``, what ``evaluate.py search_horizon=H`` plays). The states join
the data of the earlier rounds (DAgger's aggregation), and the network minimises, over
all of them, its expected regret under the planner's scores,

    sum_a pi(a | s) * (max_b Q(s, b) - Q(s, a))  +  beta * KL(pi_k(. | s) || pi(. | s)),

with ``pi_k`` the round's starting network (``--loss regret``). ``--loss crash`` pulls
only where the planner's branches decide a crash: at states where some action's branch
crashes within the horizon and another's does not, the target is the round's starting
distribution over the actions that do not crash (weighted by ``--weight``); every other
state keeps its KL to the start. ``--loss both`` adds the regret where no action's branch
crashes (speed without a crash at stake). Unlike hard argmax labels, tied actions
cost nothing (no index bias), and a state pulls in proportion to what the network's
choice loses there: the crash-scale corrections weigh more than the many small ones
(``search_labels.py`` measures both). With ``--copies K`` the planner scores each action
by its mean over K copies of the state with the other drivers' hidden variables redrawn
(``bench_hidden_search.py``, ``--redraw all``; a branch counts as crashing where more
than half of its copies crash): labels that hold only what the observation shows.

After each round the network is evaluated greedily over ``--eval-episodes``
tensor-simulator episodes from highway-env's starts of seeds 60000.. (used for nothing
else) and saved as ``<out>/round_<k>.pt``, a
checkpoint ``scripts/evaluate.py`` reads. Frames: the planner's branch steps and the
driven steps, counted as training counts them.
"""

from __future__ import annotations

import argparse
import copy
import json
import warnings
from pathlib import Path

import torch
from bench_hidden_search import RedrawnSearch
from omegaconf import OmegaConf
from search_labels import visit
from tensordict import TensorDict

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import make_env
from torchrl_grpo.training.checkpoint import load_checkpoint, save_checkpoint
from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.pretrained import load_run_policy
from torchrl_grpo.training.transfer import evaluate_on_tensor

warnings.filterwarnings("ignore")


def regret_loss(
    logits: torch.Tensor, scores: torch.Tensor, start_logits: torch.Tensor, beta: float
) -> torch.Tensor:
    """Mean expected regret under the scores, plus ``beta`` times the KL to the start."""
    regret = (scores.max(-1, keepdim=True).values - scores).to(logits.dtype)
    log_p = logits.log_softmax(-1)
    expected = (log_p.exp() * regret).sum(-1)
    start = start_logits.log_softmax(-1)
    kl = (start.exp() * (start - log_p)).sum(-1)
    return (expected + beta * kl).mean()


def crash_loss(
    logits: torch.Tensor,
    crashed: torch.Tensor,
    start_logits: torch.Tensor,
    weight: float,
    scores: torch.Tensor | None = None,
    beta: float = 0.0,
    speed: float = 1.0,
    temperature: float = 0.0,
) -> torch.Tensor:
    """Off the actions whose branch crashes where another's does not; as it was elsewhere.

    At a deciding state (some action's branch crashes within the horizon, another's does
    not) the target is the start's distribution over the actions that do not crash,
    weighted by ``weight``. At every other state: the KL to the start, and, with
    ``scores``, where no branch crashes, ``speed`` times the expected regret plus ``beta``
    times the KL. A ``temperature`` > 0 tilts the deciding states' target towards the
    safe actions that score more: the start's distribution times ``exp(score / T)``.
    """
    safe = ~crashed
    deciding = crashed.any(-1) & safe.any(-1)
    log_p = logits.log_softmax(-1)
    start = start_logits.log_softmax(-1)
    kl = (start.exp() * (start - log_p)).sum(-1)
    # Masked only where some action is safe (a row of -inf would give NaN gradients).
    tilted = start
    if temperature > 0 and scores is not None:
        tilted = (
            start + (scores - scores.max(-1, keepdim=True).values).to(start.dtype) / temperature
        )
    target = tilted.masked_fill(~safe & deciding[:, None], float("-inf")).softmax(-1)
    cross_entropy = -(target * log_p).sum(-1)
    other = kl
    if scores is not None and speed > 0:
        regret = (scores.max(-1, keepdim=True).values - scores).to(logits.dtype)
        calm = safe.all(-1)
        other = torch.where(calm, speed * (log_p.exp() * regret).sum(-1) + beta * kl, kl)
    return torch.where(deciding, weight * cross_entropy, other).mean()


def fit(policy, data: dict[str, torch.Tensor], args: argparse.Namespace) -> float:
    """Minimise ``args.loss``'s loss over ``data``; the last epoch's mean loss."""
    obs = data["observation"]
    with torch.no_grad():
        start = logits_of(policy, obs)
    optim = torch.optim.Adam(policy.parameters(), lr=args.lr)
    n, last = obs.shape[0], 0.0
    for _ in range(args.epochs):
        total = 0.0
        for idx in torch.randperm(n).split(1024):
            logits = logits_of(policy, obs[idx])
            if args.loss == "crash":
                loss = crash_loss(
                    logits, data["crashed"][idx], start[idx], args.weight,
                    data["scores"][idx] if args.temperature > 0 else None,
                    temperature=args.temperature, speed=0.0,
                )  # fmt: skip
            elif args.loss == "both":
                crashed, scores = data["crashed"][idx], data["scores"][idx]
                loss = crash_loss(
                    logits, crashed, start[idx], args.weight, scores, args.beta, args.speed
                )
            else:
                loss = regret_loss(logits, data["scores"][idx], start[idx], args.beta)
            optim.zero_grad()
            loss.backward()
            optim.step()
            total += float(loss) * len(idx)
        last = total / n
    return last


def logits_of(policy, obs: torch.Tensor) -> torch.Tensor:
    return policy(TensorDict(observation=obs, batch_size=[obs.shape[0]]))["logits"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--eval-episodes", type=int, default=1000)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--beta", type=float, default=0.05)
    parser.add_argument("--loss", choices=["regret", "crash", "both"], default="regret")
    parser.add_argument("--weight", type=float, default=1.0, help="--loss crash: deciding states")
    parser.add_argument("--speed", type=float, default=1.0, help="--loss both: the regret's scale")
    parser.add_argument("--temperature", type=float, default=0.0, help="tilt to safe scores")
    parser.add_argument(
        "--copies", type=int, default=0,
        help="> 0: the planner scores each action over this many copies of the state with "
        "the other drivers' hidden variables redrawn (bench_hidden_search.py, --redraw all)",
    )  # fmt: skip
    parser.add_argument(
        "--wide-targets", action="store_true",
        help="--copies: target speeds from the whole spawn range (bench_hidden_search.py)",
    )  # fmt: skip
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = load_checkpoint(args.checkpoint)
    env_cfg = OmegaConf.create(ckpt["config"])["env"]
    policy = load_run_policy(args.checkpoint, env_cfg, make_env(env_cfg, seed=0))
    greedy = DeterministicActor(policy)
    config = env_overrides(env_cfg)  # the run's config overrides, its observation among them

    def evaluate(label: str) -> dict:
        res = evaluate_on_tensor(env_cfg, greedy, episodes=args.eval_episodes, seed=60_000)
        summary = res.summary()
        row = {"round": label, "return": summary["return"], "crash_rate": summary["crash_rate"]}
        print(json.dumps(row), flush=True)
        return row

    history = [evaluate("start")]
    data: dict[str, list[torch.Tensor]] = {"observation": [], "scores": [], "crashed": []}
    frames = 0
    for k in range(args.rounds):
        seeds = list(range(40_000 + k * args.episodes, 40_000 + (k + 1) * args.episodes))
        planner = None
        if args.copies > 0:
            rows = 5 * args.copies * args.episodes
            planner = RedrawnSearch(
                TensorHighwayEnv(str(env_cfg.scenario), config, num_envs=rows), args.horizon,
                copies=args.copies, redraw="all", aggregate="mean", crash_penalty=0.0,
                seed=40_000 + k, base=policy, wide_targets=args.wide_targets,
            )  # fmt: skip
        visited = visit(greedy, str(env_cfg.scenario), seeds, args.horizon, 40, planner, config)
        m = visited["scores"].shape[0]
        # Driven steps, and at most 5 x H per state and copy.
        frames += m * (1 + 5 * args.horizon * max(1, args.copies))
        for key in data:
            data[key].append(visited[key])
        merged = {key: torch.cat(value) for key, value in data.items()}
        loss = fit(policy, merged, args)
        crashed = merged["crashed"]
        row_deciding = float((crashed.any(-1) & ~crashed.all(-1)).float().mean())
        row = evaluate(str(k + 1))
        row.update(states=int(merged["scores"].shape[0]), loss=loss, frames_at_most=frames)
        row.update(deciding=row_deciding)
        history.append(row)
        save_round(ckpt, policy, out, k + 1, history)


def save_round(ckpt: dict, policy, out: Path, k: int, history: list[dict]) -> None:  # noqa: ANN001
    """The run's checkpoint with ``policy``'s weights as ``<out>/round_<k>.pt``, and the
    rounds so far as ``<out>/history.json``."""
    saved = copy.copy(ckpt)
    saved["policy"] = policy.state_dict()
    save_checkpoint(saved, out / f"round_{k}.pt")
    (out / "history.json").write_text(json.dumps(history, indent=1))


if __name__ == "__main__":
    main()
