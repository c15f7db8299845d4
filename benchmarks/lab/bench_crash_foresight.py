"""Does a crash head see a policy's crashes coming, and while another action avoids them?

A crash head (``model.crash_head``) gives every action's probability of a crash. A
larger ``model.crash_aversion`` can only lower a policy's crash rate where the head
both rates the coming crash as likely and rates another action as safer. This
benchmark drives ``--checkpoint``'s greedy policy through ``--episodes`` episodes on
the tensor simulator (the starting worlds of highway-env's seeds ``--seed``.., as
``bench_crash_rates.py``) and scores each of its decisions with the crash heads of
``--head`` (each a checkpoint, several: their mean crash logits, as a ``Teachers``
labels a student; default: the driving checkpoint's own head). It prints, over all
decisions and at each of the ``--look-back`` decisions before every crash: the mean
crash probability of the chosen action, that of the action the heads call safest, and
the share of decisions where the safest is lower by at least ``--margin``.

    python benchmarks/lab/bench_crash_foresight.py --checkpoint runs/crash7_s0/last.pt
    python benchmarks/lab/bench_crash_foresight.py --checkpoint runs/distill9h_s0/last.pt \
        --head runs/h8_s0/last.pt --head runs/h8_s1/last.pt
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from bench_crash_rates import trained
from omegaconf import OmegaConf

from torchrl_grpo.modules import PolicyEnsemble
from torchrl_grpo.training.teacher_loading import has_crash_head
from torchrl_grpo.training.transfer import tensor_episodes

logging.basicConfig(level=logging.INFO, format="%(message)s")


@dataclass
class Foresight:
    """What a head says about the decisions ``k`` steps before each crash (``k = None``: all).

    Attributes:
        k: decisions before the crash (0: the last one), ``None`` for every decision.
        count: decisions scored.
        chosen: mean crash probability of the action taken.
        safest: mean crash probability of the action the head calls safest.
        avoidable: share of those decisions where the safest is lower by the margin.
    """

    k: int | None
    count: int
    chosen: float
    safest: float
    avoidable: float


def foresight(
    crash_prob: torch.Tensor,
    action: torch.Tensor,
    steps: torch.Tensor,
    crashed: torch.Tensor,
    look_back: int = 5,
    margin: float = 0.1,
) -> list[Foresight]:
    """Score every decision, then the ``look_back`` last ones before each crash.

    Args:
        crash_prob: ``[episodes, T, n_actions]`` crash probabilities of each action.
        action: ``[episodes, T]`` the actions taken.
        steps: ``[episodes, T]`` whether the step belongs to its episode.
        crashed: ``[episodes, T]`` whether the step ended in a crash.
        look_back: decisions scored before each crash.
        margin: how much lower the safest action's probability must be for the crash
            to count as avoidable by the head's reckoning.

    Returns:
        The row of all decisions (``k=None``), then one row per ``k`` in
        ``0..look_back-1`` (episodes whose crash came sooner than ``k`` are left out).

    Example:
        >>> p = torch.tensor([[[0.1, 0.3], [0.2, 0.6]]])  # one episode, two steps
        >>> rows = foresight(p, torch.tensor([[0, 1]]), torch.ones(1, 2, dtype=torch.bool),
        ...                  torch.tensor([[False, True]]), look_back=2)
        >>> [(r.k, r.count, round(r.chosen, 2), round(r.safest, 2), r.avoidable) for r in rows]
        [(None, 2, 0.35, 0.15, 0.5), (0, 1, 0.6, 0.2, 1.0), (1, 1, 0.1, 0.1, 0.0)]
    """
    chosen = crash_prob.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
    safest = crash_prob.min(-1).values

    def row(k: int | None, mask: torch.Tensor) -> Foresight:
        c, s = chosen[mask].double(), safest[mask].double()
        n = int(mask.sum())
        mean = (lambda x: float(x.mean())) if n else (lambda x: float("nan"))
        return Foresight(k, n, mean(c), mean(s), mean((c - s >= margin).double()))

    rows = [row(None, steps)]
    hits = crashed & steps
    ended = hits.any(1)
    at = hits.long().argmax(1)  # the crash's step, per crashed episode
    for k in range(look_back):
        mask = torch.zeros_like(steps)
        which = ended & (at >= k)
        mask[which.nonzero().squeeze(-1), (at - k)[which]] = True
        rows.append(row(k, mask))
    return rows


def crash_net(paths: list[str]) -> torch.nn.Module:
    """The crash logits of ``paths``' networks: one network's, or their mean."""
    nets = []
    for path in paths:
        net = trained(path)[1].module[0].module
        if not has_crash_head(net):
            raise SystemExit(f"{path} has no crash head (trained with model.crash_head=false)")
        nets.append(net)
    return (nets[0] if len(nets) == 1 else PolicyEnsemble(nets)).eval()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="the run whose greedy policy drives")
    p.add_argument("--head", action="append", default=[], help="a run whose crash head scores")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=30_000, help="first episode's seed")
    p.add_argument("--look-back", type=int, default=5, help="decisions scored per crash")
    p.add_argument("--margin", type=float, default=0.1, help="'avoidable': safest lower by this")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    env_cfg, policy = trained(args.checkpoint)
    env_cfg = OmegaConf.merge(env_cfg, {"max_episode_steps": env_cfg.get("max_episode_steps", 40)})
    heads = args.head or [args.checkpoint]
    data, steps = tensor_episodes(env_cfg, policy, episodes=args.episodes, seed=args.seed)
    with torch.no_grad():
        crash_prob = torch.sigmoid(crash_net(heads).crash_logits(data.get("observation")))
    crashed = data.get(("next", "crashed")).reshape(steps.shape)
    rows = foresight(
        crash_prob,
        data.get("action").reshape(steps.shape),
        steps,
        crashed,
        look_back=args.look_back,
        margin=args.margin,
    )
    print(
        f"{args.checkpoint} driving {args.episodes} episodes from seeds {args.seed}.. "
        f"({int((crashed & steps).any(1).sum())} crashes), scored by the crash heads of "
        f"{', '.join(heads)}"
    )
    print(f"| decisions | count | p(chosen) | p(safest) | safest lower by >= {args.margin:g} |")
    print("|---|---|---|---|---|")
    for r in rows:
        when = "all" if r.k is None else f"{r.k} before the crash"
        print(f"| {when} | {r.count} | {r.chosen:.3f} | {r.safest:.3f} | {r.avoidable:.2f} |")


if __name__ == "__main__":
    main()
