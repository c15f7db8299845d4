"""Is cloning the search short of states, of width, or of a loss? Learning curves.

    T=runs/<run>/last.pt
    python benchmarks/lab/search_clone_scale.py label --tail $T --worlds 10000 \\
        --seed 100000 --native --out <dir>/labels_100000.pt       # one process a seed range
    python benchmarks/lab/search_clone_scale.py fit --tail $T --labels <dir>/labels_*.pt \\
        --fractions 0.0625 0.25 1 --widths 256 1024 [--danger-weights 0 100] --drive 1000
    python benchmarks/lab/search_clone_scale.py dagger --tail $T --labels <dir>/labels_*.pt \\
        --danger-weights 100 --rounds 3 --worlds 4000 --epsilon 0.1 --seed 200000 \\
        --native --drive 1000 --out <dagger dir>
    python benchmarks/lab/search_clone_scale.py ensemble --tail $T --labels <dir>/labels_*.pt \\
        --test <a label file of other seeds> --members 3 --danger-weights 100 --out <dir>
    python benchmarks/lab/search_clone_scale.py heldout --tail $T \\
        --net <dagger dir>/round_3.pt --episodes 1000 --seed 150000 [--aversion 200] \\
        [--ppo <PPO run>/last.pt]

``label`` lets the search (every action tried, then ``--horizon - 1`` greedy steps of
the ``--tail`` run, rows of the tensor simulator, from the whole state) drive
``--worlds`` episodes from highway-env's starts of ``--seed, --seed + 1, ...``, ``--chunk``
of them at a time, with a random action on a fraction ``--epsilon`` of the steps so that
the states spread (``label_inputs.labelled_states``; ``--native``: on the C++
substeps). It keeps, at every state, the run's observation, every action's branch
return and whether that branch crashed.

``fit`` pools label files (their seed ranges must not overlap), holds out a tenth of
the states, and fits a fresh MLP from the observation to the search's best set
(``label_inputs.fit``: ``--epochs`` passes of 256 states a step, at most ``--max-steps``
steps) on a fraction of the rest, for every hidden width, danger weight and fraction.
``--danger-weights w`` adds ``w`` times the probability the fit gives the actions whose
branch crashes where another's does not. For each fit, and for the run's own greedy
network on the same held-out states, it prints:

* the accuracy (argmax in the best set) and the regret (best return less the argmax's);
* the share of states where the argmax loses more than 1, about a crash within the horizon;
* the crash error: the share where the argmax's branch crashes and another action's
  does not, the error that costs an episode, which the regret mixes with slowness.

With ``--drive N`` the fit of all the states drives greedily over ``N``
tensor-simulator episodes from highway-env's starts of seeds 40000.., beside the run's
network (``label_inputs.drive``).

``dagger`` fits every label so far (at the first width and danger weight), saves the
fit as ``round_<r>.pt``, drives it as ``--drive`` does, and labels ``--worlds`` episodes
of its own driving from ``--seed`` on, round after round. ``ensemble`` fits
``--members`` networks on every label, one seed each, and scores each and the mean of
their logits on ``--test``, a label file of episodes that none of them saw: if the
mean errs much less than its members, their errors are the fit's variance. ``heldout``
drives a saved fit on highway-env itself, paired against the run and always-SLOWER.
"""

from __future__ import annotations

import argparse
import itertools
import time
import warnings
from collections.abc import Callable

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from label_inputs import _Greedy, _RunLogits, drive, fit, labelled_states
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torch import nn

from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training import make_env
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.env_builder import make_layout
from torchrl_grpo.training.evaluation import baseline_policy, evaluate
from torchrl_grpo.training.pretrained import load_run_policy
from torchrl_grpo.training.results import compare_paired

warnings.filterwarnings("ignore")


def label_range(
    args: argparse.Namespace,
    seed: int,
    worlds: int,
    behaviour: nn.Module | None = None,
    extra: Callable[[TensorDictBase], dict[str, torch.Tensor]] | None = None,
) -> dict[str, torch.Tensor]:
    """The labelled states of ``worlds`` episodes from ``seed`` on, ``args.chunk`` at a time.

    ``extra``: more columns, computed from each chunk's full states (kept only for it)."""
    parts: dict[str, list[torch.Tensor]] = {}
    start = time.perf_counter()
    for first in range(seed, seed + worlds, args.chunk):
        count = min(args.chunk, seed + worlds - first)
        scenario, obs, states, scores, crashed = labelled_states(
            "",
            args.tail,
            count,
            args.epsilon,
            args.horizon,
            first,
            keep_states=extra is not None,
            native=args.native,
            behaviour=behaviour,
        )
        columns = {"observation": obs.float(), "scores": scores, "crashed": crashed}
        for key, value in (columns | (extra(states) if extra else {})).items():
            parts.setdefault(key, []).append(value)
        done = sum(len(s) for s in parts["scores"])
        minutes = (time.perf_counter() - start) / 60
        print(f"{scenario}: seeds {seed}..{first + count - 1}, {done} states, {minutes:.1f} min")
    labels = {key: torch.cat(value) for key, value in parts.items()}
    labels["seeds"] = torch.tensor([seed, seed + worlds])
    return labels


def errors(logits: torch.Tensor, scores: torch.Tensor, crashed: torch.Tensor) -> dict[str, float]:
    """What the argmax of ``logits`` costs against the search's scores and crash flags."""
    chosen = logits.argmax(-1, keepdim=True)
    best = scores >= scores.amax(-1, keepdim=True) - 1e-6
    regret = scores.amax(-1) - scores.gather(1, chosen).squeeze(-1)
    crash = crashed.gather(1, chosen).squeeze(-1) & ~crashed.all(-1)
    return {
        "accuracy": float(best.gather(1, chosen).float().mean()),
        "regret": float(regret.mean()),
        "regret > 1": float((regret > 1).float().mean()),
        "crash error": float(crash.float().mean()),
    }


def pool(files: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Label sets pooled; their seed ranges (``seeds``, ``[sets, 2]``) must be disjoint."""
    ranges = sorted(tuple(f["seeds"].tolist()) for f in files)
    for (_, end), (begin, _) in zip(ranges, ranges[1:], strict=False):
        if begin < end:
            raise SystemExit(f"label files share seeds: {ranges}")
    pooled = {
        key: torch.cat([f[key] for f in files]) for key in ("observation", "scores", "crashed")
    }
    return pooled | {"seeds": torch.tensor(ranges)}


def held_out_split(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The states ``fit`` holds out (a tenth, drawn with seed 0) and the rest, in order."""
    split = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    return split[: n // 10], split[n // 10 :]


def load_labels(paths: list[str]) -> dict[str, torch.Tensor]:
    """The label files pooled (:func:`pool`)."""
    return pool([torch.load(path) for path in paths])


def fit_curve(args: argparse.Namespace) -> None:
    """The fits over ``args.fractions`` and ``args.widths``; their errors and drives."""
    torch.set_num_threads(args.threads)
    labels = load_labels(args.labels)
    obs, scores, crashed = labels["observation"], labels["scores"], labels["crashed"]
    x = obs.flatten(1)
    n = len(scores)
    test, pool = held_out_split(n)
    cfg = _env_of(args.tail)
    print(
        f"{n} states, {len(test)} held out; the search's best set crashes on "
        f"{float(crashed.gather(1, scores.argmax(-1, keepdim=True)).float().mean()):.2%}\n"
    )
    _table_head(args.tail, cfg, obs[test], scores[test], crashed[test])
    danger = _danger(crashed)
    grid = itertools.product(args.widths, args.danger_weights, args.fractions)
    for width, weight, fraction in grid:
        fitted = pool[: int(fraction * len(pool))]
        start = time.perf_counter()
        epochs = _epochs(args, len(fitted))
        _, net = fit(
            x, scores, fitted, test, epochs, width=width, danger=danger, danger_weight=weight
        )
        minutes = (time.perf_counter() - start) / 60
        with torch.no_grad():
            figures = errors(net(x[test]), scores[test], crashed[test])
        name = f"MLP {width}x2" + (f", danger weight {weight:g}" if weight else "")
        print(_row(name, len(fitted), minutes, figures), flush=True)
        if args.drive and fraction == max(args.fractions):
            drive(str(cfg.scenario), args.tail, net, args.drive)


def dagger(args: argparse.Namespace) -> None:
    """Rounds of DAgger: fit every label so far, drive the fit, label the states it visits."""
    torch.set_num_threads(args.threads)
    sets = [torch.load(path) for path in args.labels]
    cfg = _env_of(args.tail)
    for round_ in range(1, args.rounds + 1):
        net, states, epochs = _fit_every(args, pool(sets))
        torch.save(net, f"{args.out}/round_{round_}.pt")
        print(f"round {round_}: fitted {states} states ({epochs} epochs)", flush=True)
        if args.drive:
            drive(str(cfg.scenario), args.tail, net, args.drive)
        seed = args.seed + (round_ - 1) * args.worlds
        sets.append(label_range(args, seed, args.worlds, _Greedy(net)))
        torch.save(sets[-1], f"{args.out}/labels_{seed}.pt")


def _fit_every(
    args: argparse.Namespace, labels: dict[str, torch.Tensor], seed: int = 0
) -> tuple[nn.Module, int, int]:
    """A fresh fit of every labelled state (at the first width and danger weight); the fit,
    the number of states and of epochs."""
    x, scores = labels["observation"].flatten(1), labels["scores"]
    every = torch.arange(len(scores))
    epochs = _epochs(args, len(every))
    _, net = fit(
        x,
        scores,
        every,
        every[:1],
        epochs,
        width=args.widths[0],
        danger=_danger(labels["crashed"]),
        danger_weight=args.danger_weights[0],
        seed=seed,
    )
    return net, len(every), epochs


class MeanLogits(nn.Module):
    """Several fits as one network: the mean of their logits."""

    def __init__(self, nets: list[nn.Module]) -> None:
        super().__init__()
        self.nets = nn.ModuleList(nets)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([net(x) for net in self.nets]).mean(0)


def ensemble(args: argparse.Namespace) -> None:
    """``args.members`` fits of every label, one seed each, scored alone and as their mean.

    The scores are on the label file ``args.test``, whose episodes no fit saw; the mean
    of the logits drives as ``--drive`` does. If the members err on different states,
    their mean errs less: the errors are the fit's variance, not what the network can
    represent.
    """
    torch.set_num_threads(args.threads)
    labels, held = load_labels(args.labels), load_labels([args.test])
    begin, end = held["seeds"][0].tolist()
    if any(b < end and begin < e for b, e in labels["seeds"].tolist()):
        raise SystemExit(f"{args.test} shares seeds with the fitted labels")
    tx, ts, tc = held["observation"].flatten(1), held["scores"], held["crashed"]
    cfg = _env_of(args.tail)
    print(f"{len(tx)} held-out states of seeds {begin}..{end - 1}\n")
    _table_head(args.tail, cfg, held["observation"], ts, tc)
    nets = []
    for seed in range(args.members):
        start = time.perf_counter()
        net, states, _ = _fit_every(args, labels, seed)
        torch.save(net, f"{args.out}/member_{seed}.pt")
        nets.append(net)
        minutes = (time.perf_counter() - start) / 60
        with torch.no_grad():
            print(_row(f"member, seed {seed}", states, minutes, errors(net(tx), ts, tc)))
    mean = MeanLogits(nets)
    with torch.no_grad():
        print(_row(f"mean of {len(nets)} members", states, 0.0, errors(mean(tx), ts, tc)))
    if args.drive:
        drive(str(cfg.scenario), args.tail, mean, args.drive)


def heldout(args: argparse.Namespace) -> None:
    """The fit ``args.net`` (several: their mean logits) on highway-env itself, paired
    against always-SLOWER, the rule policy, the run and ``--ppo`` (a PPO run of the same
    observation)."""
    cfg = _env_of(args.tail)
    highway = make_env(cfg)
    layout, actions = make_layout(highway), int(highway.action_spec.n)
    policies = {
        "always-SLOWER": baseline_policy("slower", layout, actions),
        "the rule policy": baseline_policy("rule", layout, actions),
        "the run, greedy": DeterministicActor(load_run_policy(args.tail, cfg, highway)),
    }
    if args.ppo:
        policies["PPO, greedy"] = DeterministicActor(
            load_run_policy(args.ppo, cfg, highway, role="--ppo")
        )
    policies["the fit, greedy"] = _Greedy(MeanLogits([_load_fit(p, args) for p in args.net]))
    results = {}
    for name, policy in policies.items():
        results[name], _ = evaluate(
            highway, policy, episodes=args.episodes, seed=args.seed, name=name, workers=args.workers
        )
        summary = results[name].summary()
        print(
            f"- {name}: {summary['return']:.2f} ± {summary['return_sem']:.2f} / "
            f"{summary['crash_rate']:.1%} on highway-env, seeds {args.seed}.."
        )
    for other in list(policies)[:-1]:
        print(f"- {compare_paired(results['the fit, greedy'], results[other])}")


def _load_fit(path: str, args: argparse.Namespace) -> nn.Module:
    # A saved fit; ``--aversion`` sets how one with a crash head (clone_heads.py) acts.
    net = torch.load(path, weights_only=False)
    if args.aversion is not None:
        if getattr(net, "crash", None) is None:
            raise SystemExit(f"{path} has no crash head for --aversion to weigh")
        net.aversion = args.aversion
    return net


def _danger(crashed: torch.Tensor) -> torch.Tensor:
    # The actions whose branch crashes where another action's does not.
    return (crashed & ~crashed.all(-1, keepdim=True)).float()


def _epochs(args: argparse.Namespace, states: int) -> int:
    # Past --max-steps updates of 256 states, a larger set gets fewer epochs.
    return min(args.epochs, max(1, round(args.max_steps * 256 / states)))


def _env_of(tail: str) -> DictConfig:
    # The run's env config: its scenario and its observation.
    return OmegaConf.create(load_checkpoint(tail)["config"])["env"]


def _table_head(
    tail: str, cfg: DictConfig, obs: torch.Tensor, scores: torch.Tensor, crashed: torch.Tensor
) -> None:
    # The table's header, and its first row: the run's own network on the held-out states.
    run = _RunLogits(load_run_policy(tail, cfg, make_env(cfg)), obs.shape[1:])
    print("| network | states fitted | minutes | accuracy | regret | > 1 | crash error |")
    print("|---|---|---|---|---|---|---|")
    with torch.no_grad():
        print(_row("the run, greedy", "-", 0.0, errors(run(obs.flatten(1)), scores, crashed)))


def _row(name: str, fitted: object, minutes: float, e: dict[str, float]) -> str:
    return (
        f"| {name} | {fitted} | {minutes:.1f} | {e['accuracy']:.3f} | {e['regret']:.3f} | "
        f"{e['regret > 1']:.2%} | {e['crash error']:.2%} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["label", "fit", "dagger", "ensemble", "heldout"])
    parser.add_argument("--tail", required=True, help="the run whose greedy tails the search takes")
    parser.add_argument("--worlds", type=int, default=8000)
    parser.add_argument("--chunk", type=int, default=1000)
    parser.add_argument("--epsilon", type=float, default=0.3)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--seed", type=int, default=70_000)
    parser.add_argument("--native", action="store_true", help="label on the C++ substeps")
    parser.add_argument("--out", help="label: the file of labels; dagger, ensemble: a folder")
    parser.add_argument("--rounds", type=int, default=3, help="dagger: rounds")
    parser.add_argument(
        "--net", nargs="+", help="heldout: fits that dagger or ensemble saved (several: their mean)"
    )
    parser.add_argument("--members", type=int, default=3, help="ensemble: fits, one seed each")
    parser.add_argument("--test", help="ensemble: a label file of episodes no fit saw")
    parser.add_argument("--episodes", type=int, default=1000, help="heldout: highway-env episodes")
    parser.add_argument("--workers", type=int, default=2, help="heldout: processes")
    parser.add_argument("--ppo", help="heldout: a PPO run's last.pt, of the run's observation")
    parser.add_argument(
        "--aversion", type=float, help="heldout: how fits with a crash head act (default: as saved)"
    )
    parser.add_argument("--labels", nargs="+", help="fit, dagger, ensemble: label files")
    parser.add_argument("--fractions", type=float, nargs="+", default=[0.0625, 0.25, 1.0])
    parser.add_argument("--widths", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument(
        "--danger-weights", type=float, nargs="+", default=[0.0], help="fit: expected-crash weights"
    )
    parser.add_argument("--max-steps", type=int, default=20_000, help="updates a fit at most")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--drive", type=int, default=0, help="tensor-simulator episodes a fit drives"
    )
    args = parser.parse_args()
    if args.stage == "label":
        torch.set_num_threads(1)
        torch.save(label_range(args, args.seed, args.worlds), args.out)
    elif args.stage == "fit":
        fit_curve(args)
    elif args.stage == "dagger":
        dagger(args)
    elif args.stage == "ensemble":
        ensemble(args)
    else:
        heldout(args)


if __name__ == "__main__":
    main()
