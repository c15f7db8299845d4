"""Does the network's form close the clone's crash errors? Its inputs and a crash head.

    T=runs/<run>/last.pt
    python benchmarks/lab/clone_heads.py fit --tail $T --labels <dir>/labels_*.pt \\
        --trunks flat scene attention --crash-weights 0 1 --aversions 0 3 10 30 \\
        [--margins 0.02] [--max-steps 60000 --cosine] [--drive 1000 --act-aversion 30] \\
        [--out <fits>]
    python benchmarks/lab/clone_heads.py drive --tail $T --net <fits>/<fit>.pt \\
        --act-aversion 100 [300 1000] --drive 1000
    python benchmarks/lab/clone_heads.py score --tail $T --labels <dir>/labels_*.pt \\
        --net <fits>/<fit>.pt --aversions 30 100
    python benchmarks/lab/clone_heads.py dagger --tail $T --labels <dir>/labels_*.pt \\
        --trunks attention --crash-weights 1 --max-steps 60000 --cosine --act-aversion 100 \\
        [--first <fits>/<fit>.pt] --rounds 3 --worlds 4000 --seed 200000 --native \\
        --drive 1000 --out <dagger dir>

The labels are ``search_clone_scale.py label``'s: at each state the run's observation,
every action's branch return under the search, and whether that branch crashed. Its
fits, over the flat table, err into crashes ten times as often as the run whose search
they clone, and a weight on the expected crash levels their errors at 0.35% of the
states. Two things the run has and those fits lack:

* **inputs**: the run reads driving features of the scene (gaps, closing speeds, room
  to change lane), not the table alone; an attention network shares one function of a
  vehicle across the rows (``clone_nets.make_trunk``);
* **a crash head**: the run's net has a second output per action, its chance of
  crashing, and acts on ``policy + 3 log(1 - p_crash)``. Here the head is fitted to the
  search's crash flags (binary cross-entropy, ``--crash-weights`` of it beside the
  cross-entropy to the search's best set).

``fit`` holds out a tenth of the pooled states (the split of ``search_clone_scale.py
fit``), fits every trunk, crash weight and danger weight on the rest, and scores the
fits on the held-out states at every ``--aversions`` (and ``--margins``: the actions
whose crash chance exceeds the smallest by more bar), beside the run. A fit runs
``--epochs`` passes of 256 states a step, at most ``--max-steps`` steps, Adam at 1e-3
(``--cosine``: decaying to 0 on a cosine; ``--lr``: another rate). ``--layers`` sets the
transformer's depth; ``--init`` starts each fit from a saved fit instead of a fresh
net; ``--regret-weight`` adds the policy's expected regret to the loss. ``--drive N``
drives each fit at ``--act-aversion`` (and ``--act-margin``) over ``N``
tensor-simulator episodes from highway-env's starts of seeds 40000... ``dagger`` is
``search_clone_scale.py dagger`` with these nets: it fits every label so far at the
first trunk and weights, drives, and labels ``--worlds`` episodes of its own driving
(``--first``: a fit of the given labels made already stands for the first round).
``drive --net <out>/<fit>.pt`` drives a saved fit (several: their mean logits) as
``--drive`` does, at other weights (several ``--act-aversion``: each, over the same
episodes, the run driven once); ``score --net <fits>`` scores saved fits on the
held-out and on fitted states, beside the run with and without its crash head.
``search_clone_scale.py heldout --net <out>/<fit>.pt`` drives a fit on highway-env.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import time
import warnings

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from clone_nets import TRUNKS, CloneNet, make_trunk
from label_inputs import _Greedy, drive
from omegaconf import DictConfig
from search_clone_scale import (
    MeanLogits,
    _danger,
    _env_of,
    _epochs,
    _row,
    _table_head,
    errors,
    held_out_split,
    label_range,
    load_labels,
    pool,
)
from torch.nn import functional as F

from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.training import make_env
from torchrl_grpo.training.env_builder import make_layout
from torchrl_grpo.training.pretrained import load_run_policy

warnings.filterwarnings("ignore")


def fit_net(
    net: CloneNet,
    labels: dict[str, torch.Tensor],
    rows: torch.Tensor,
    epochs: int,
    danger_weight: float,
    crash_weight: float,
    seed: int = 0,
    cosine: bool = False,
    lr: float = 1e-3,
    regret_weight: float = 0.0,
) -> CloneNet:
    """Fits ``net`` on ``labels[rows]``: the best set's cross-entropy, the expected crash
    times ``danger_weight``, the crash head's cross-entropy times ``crash_weight`` and the
    expected regret (what the policy's choice loses to the best branch) times
    ``regret_weight``.

    Adam at ``lr``, ``epochs`` passes of 256 states a step; ``cosine``: the rate decays
    to 0 along a cosine over the passes."""
    x, scores, crashed = labels["observation"].flatten(1), labels["scores"], labels["crashed"]
    best = (scores >= scores.amax(-1, keepdim=True) - 1e-6).float()
    target = best / best.sum(-1, keepdim=True)
    danger = _danger(crashed)
    gap = scores.amax(-1, keepdim=True) - scores
    optim = torch.optim.Adam(net.parameters(), lr=lr)
    steps = epochs * -(-len(rows) // 256)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optim, steps) if cosine else None
    order = torch.Generator().manual_seed(1 + seed)
    for _ in range(epochs):
        for batch in rows[torch.randperm(len(rows), generator=order)].split(256):
            logits, crash = net.heads(x[batch])
            log_p = logits.log_softmax(-1)
            loss = -(target[batch] * log_p).sum(-1).mean()
            if danger_weight:
                loss = loss + danger_weight * (log_p.exp() * danger[batch]).sum(-1).mean()
            if regret_weight:
                loss = loss + regret_weight * (log_p.exp() * gap[batch]).sum(-1).mean()
            if crash is not None:
                flags = crashed[batch].float()
                loss = loss + crash_weight * F.binary_cross_entropy_with_logits(crash, flags)
            optim.zero_grad()
            loss.backward()
            optim.step()
            if schedule is not None:
                schedule.step()
    return net


def new_net(
    args: argparse.Namespace,
    layout: KinematicsLayout,
    trunk: str,
    crash_weight: float,
    x: torch.Tensor,
    actions: int,
) -> CloneNet:
    """A fresh :class:`CloneNet` (a crash head where ``crash_weight`` > 0), seeded with 0;
    with ``--init``, that saved fit instead, to be fitted further."""
    if args.init:
        # Its standardisation stays the one of the states it was first fitted on.
        return torch.load(args.init, weights_only=False)
    torch.manual_seed(0)
    body = make_trunk(trunk, layout, x, args.width, args.embed, args.layers)
    return CloneNet(body, args.width, actions, crash_head=crash_weight > 0)


def _fit(args: argparse.Namespace, net: CloneNet, *fit_args: object) -> CloneNet:
    # fit_net at the command line's rate, schedule and regret weight.
    kwargs = {"cosine": args.cosine, "lr": args.lr, "regret_weight": args.regret_weight}
    return fit_net(net, *fit_args, **kwargs)


def _layout(cfg: DictConfig) -> KinematicsLayout:
    # The run's observation layout, which the trunks read.
    return make_layout(make_env(cfg))


def _name(trunk: str, crash_weight: float, danger_weight: float) -> str:
    name = trunk + (f", crash head {crash_weight:g}" if crash_weight else "")
    return name + (f", danger weight {danger_weight:g}" if danger_weight else "")


def _acting(net: CloneNet, args: argparse.Namespace, aversion: float | None = None) -> CloneNet:
    # How a fit acts: at ``aversion``, else the first of ``--act-aversion``.
    net.aversion = args.act_aversion[0] if aversion is None else aversion
    net.margin = args.act_margin
    return net


def fit_grid(args: argparse.Namespace) -> None:
    """Every trunk, crash weight and danger weight, scored at every aversion and margin."""
    torch.set_num_threads(args.threads)
    labels = load_labels(args.labels)
    obs, scores, crashed = labels["observation"], labels["scores"], labels["crashed"]
    x = obs.flatten(1)
    test, fitted = held_out_split(len(scores))
    cfg = _env_of(args.tail)
    layout = _layout(cfg)
    print(f"{len(scores)} states, {len(test)} held out\n")
    _table_head(args.tail, cfg, obs[test], scores[test], crashed[test])
    epochs = _epochs(args, len(fitted))
    grid = itertools.product(args.trunks, args.crash_weights, args.danger_weights)
    for trunk, crash_weight, danger_weight in grid:
        start = time.perf_counter()
        net = new_net(args, layout, trunk, crash_weight, x[fitted], scores.shape[1])
        _fit(args, net, labels, fitted, epochs, danger_weight, crash_weight)
        minutes = (time.perf_counter() - start) / 60
        name = _name(trunk, crash_weight, danger_weight)
        acts = [(0.0, None)] if net.crash is None else _acts(args)
        with torch.no_grad():
            for aversion, margin in acts:
                net.aversion, net.margin = aversion, margin
                figures = errors(net(x[test]), scores[test], crashed[test])
                how = "" if net.crash is None else f", aversion {aversion:g}"
                how += "" if margin is None else f", margin {margin:g}"
                print(_row(name + how, len(fitted), minutes, figures), flush=True)
        net = _acting(net, args)
        if args.out:
            file = name.replace(", ", "_").replace(" ", "-")
            torch.save(net, f"{args.out}/{file}.pt")
        if args.drive:
            drive(str(cfg.scenario), args.tail, net, args.drive)


def _acts(args: argparse.Namespace) -> list[tuple[float, float | None]]:
    margins: list[float | None] = [None, *args.margins]
    return list(itertools.product(args.aversions, margins))


def dagger(args: argparse.Namespace) -> None:
    """Rounds of DAgger with the first trunk and weights (``search_clone_scale.py dagger``)."""
    torch.set_num_threads(args.threads)
    sets = [torch.load(path) for path in args.labels]
    cfg = _env_of(args.tail)
    layout = _layout(cfg)
    trunk, crash_weight = args.trunks[0], args.crash_weights[0]
    danger_weight = args.danger_weights[0]
    for round_ in range(1, args.rounds + 1):
        if round_ == 1 and args.first:
            # A fit of these labels made already (by ``fit``) stands for the first round.
            net = _acting(torch.load(args.first, weights_only=False), args)
        else:
            labels = pool(sets)
            every = torch.arange(len(labels["scores"]))
            epochs = _epochs(args, len(every))
            x, actions = labels["observation"].flatten(1), labels["scores"].shape[1]
            net = new_net(args, layout, trunk, crash_weight, x, actions)
            _fit(args, net, labels, every, epochs, danger_weight, crash_weight)
            net = _acting(net, args)
            torch.save(net, f"{args.out}/round_{round_}.pt")
            name = _name(trunk, crash_weight, danger_weight)
            print(f"round {round_}: {name}, fitted {len(every)} states ({epochs} epochs)")
            if args.drive:
                drive(str(cfg.scenario), args.tail, net, args.drive)
        seed = args.seed + (round_ - 1) * args.worlds
        sets.append(label_range(args, seed, args.worlds, _Greedy(net)))
        torch.save(sets[-1], f"{args.out}/labels_{seed}.pt")


def drive_saved(args: argparse.Namespace) -> None:
    """Drives the saved fits ``args.net`` (several: their mean logits) at each of
    ``--act-aversion`` (and ``--act-margin``), beside the run, over the same episodes."""
    torch.set_num_threads(args.threads)
    nets = [torch.load(path, weights_only=False) for path in args.net]
    # A copy of the nets for each aversion: the drives share none of their acting weights.
    fits = {
        f"the fit at aversion {aversion:g}": MeanLogits(
            [_acting(copy.deepcopy(net), args, aversion) for net in nets]
        )
        for aversion in args.act_aversion
    }
    drive(str(_env_of(args.tail).scenario), args.tail, fits, args.drive)


def score(args: argparse.Namespace) -> None:
    """The saved fits ``args.net`` at every aversion, on the held-out tenth of ``fit``'s
    split and on 50,000 of its fitted states (equal errors on both: the fit underfits);
    the run, and its policy logits alone, without its crash head."""
    torch.set_num_threads(args.threads)
    labels = load_labels(args.labels)
    obs, scores, crashed = labels["observation"], labels["scores"], labels["crashed"]
    test, fitted = held_out_split(len(scores))
    cfg = _env_of(args.tail)
    run = load_run_policy(args.tail, cfg, make_env(cfg))
    head = next(m for m in run.modules() if isinstance(m, CrashHead))
    for where, rows in {"held out": test, "fitted": fitted[:50_000]}.items():
        x, s, c = obs[rows], scores[rows], crashed[rows]
        print(f"\n{len(rows)} {where} states\n")
        _table_head(args.tail, cfg, x, s, c)
        with torch.no_grad():
            policy = head.net(x)[..., : head.n_actions]
            print(_row("the run's policy logits alone", "-", 0.0, errors(policy, s, c)))
            for path in args.net:
                net = torch.load(path, weights_only=False)
                for aversion in args.aversions:
                    net.aversion, net.margin = aversion, None
                    name = f"{path}, aversion {aversion:g}"
                    print(_row(name, "-", 0.0, errors(net(x.flatten(1)), s, c)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["fit", "dagger", "drive", "score"])
    parser.add_argument("--tail", required=True, help="the run whose search made the labels")
    parser.add_argument("--labels", nargs="+", help="fit, dagger: label files")
    parser.add_argument("--net", nargs="+", help="drive, score: saved fits")
    parser.add_argument(
        "--trunks", nargs="+", choices=TRUNKS, default=["flat", "scene", "attention"]
    )
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--embed", type=int, default=64, help="the vehicles' embeddings")
    parser.add_argument("--layers", type=int, default=2, help="transformer: attention layers")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam's rate")
    parser.add_argument("--init", help="fit, dagger: a saved fit to fit further, not a fresh one")
    parser.add_argument("--cosine", action="store_true", help="the rate decays along a cosine")
    parser.add_argument("--crash-weights", type=float, nargs="+", default=[0.0, 1.0])
    parser.add_argument("--danger-weights", type=float, nargs="+", default=[0.0])
    parser.add_argument("--regret-weight", type=float, default=0.0, help="the expected regret")
    parser.add_argument("--aversions", type=float, nargs="+", default=[0.0, 3.0, 10.0])
    parser.add_argument("--margins", type=float, nargs="*", default=[])
    parser.add_argument(
        "--act-aversion",
        type=float,
        nargs="+",
        default=[3.0],
        help="how a saved fit acts; drive: several, each driven",
    )
    parser.add_argument("--act-margin", type=float, default=None)
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--max-steps", type=int, default=20_000, help="updates a fit at most")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--drive", type=int, default=0, help="tensor-simulator episodes")
    parser.add_argument("--out", help="fit: where the fits go; dagger: a folder")
    parser.add_argument("--rounds", type=int, default=3, help="dagger: rounds")
    parser.add_argument("--first", help="dagger: a saved fit of the labels, for the first round")
    parser.add_argument("--worlds", type=int, default=4000, help="dagger: episodes a round")
    parser.add_argument("--seed", type=int, default=200_000, help="dagger: the first seed")
    parser.add_argument("--epsilon", type=float, default=0.1, help="dagger: random actions")
    parser.add_argument("--chunk", type=int, default=1000)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--native", action="store_true", help="dagger: label on the C++ substeps")
    args = parser.parse_args()
    if args.stage != "drive" and len(args.act_aversion) > 1:
        parser.error(f"{args.stage} acts at one --act-aversion, not {args.act_aversion}")
    grid = len(args.trunks) * len(args.crash_weights) * len(args.danger_weights)
    if args.init and args.stage == "fit" and grid > 1:
        parser.error("--init fits one saved net: give one trunk, crash weight and danger weight")
    stages = {"fit": fit_grid, "dagger": dagger, "drive": drive_saved, "score": score}
    stages[args.stage](args)


if __name__ == "__main__":
    main()
