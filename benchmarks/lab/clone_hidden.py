"""Is the clone short of what the observation hides, or of fitting? Fits that see the hidden state.

    T=runs/<run>/last.pt
    python benchmarks/lab/clone_hidden.py label --tail $T --worlds 10000 --seed 100000 \\
        --native --out hidden_100000.pt
    python benchmarks/lab/clone_hidden.py fit --tail $T --labels hidden_100000.pt \\
        --max-steps 20000 [--out <dir>]

The search that ``clone_heads.py`` clones reads the whole state; its fits read the
observation. What the observation leaves out of the vehicles it shows could decide
which actions crash within the horizon, and cap what any fit of the observation
learns. ``label`` makes ``search_clone_scale.py label``'s labels (the same states,
scores and crash flags for the same seeds) and keeps, for each row of the table, the
hidden state of the vehicle it shows (:data:`HIDDEN`: the speed set-point, IDM's for
the others and the ego's own; the seconds since its last MOBIL decision; the lane it
is changing to, less the one it is in; zeros where a row shows none).

``fit`` holds out a tenth (``search_clone_scale.held_out_split``) and fits the
attention trunk with a crash head three times, from the same seed and steps: on the
observation, with the ego's hidden state beside its row, and with every shown
vehicle's. Each is scored on the held-out and on 20,000 fitted states at every
``--aversions``. If the hidden state decided the crashes, the fits that see it would
err less; if they err as the first does, on fitted as on new states, the fit, not the
observation, is what is short. Last, the crash head's calibration on the held-out
actions (its chance against the flags' frequency) and its chance for the chosen
action where the first fit errs into a crash at ``--act-aversion``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from clone_heads import fit_net, new_net
from clone_nets import CloneNet
from omegaconf import OmegaConf
from search_clone_scale import _env_of, _epochs, _row, errors, held_out_split, label_range
from tensordict import TensorDictBase

from torchrl_grpo.envs import tensor_params
from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.sim.observation import shown_vehicles
from torchrl_grpo.sim.params import HighwayParams
from torchrl_grpo.sim.state import world_from_tensordict
from torchrl_grpo.training import make_env
from torchrl_grpo.training.env_builder import make_layout

warnings.filterwarnings("ignore")

#: The hidden columns, one row per row of the observation.
HIDDEN = ("target_speed", "timer", "lane_change")


def hidden_rows(state: TensorDictBase, params: HighwayParams) -> torch.Tensor:
    """``[N, vehicles_count, 3]``: the :data:`HIDDEN` state of the vehicle each row of the
    observation shows (row 0 the ego), zeros where a row shows none."""
    v = world_from_tensordict(state).vehicles
    order, shown = shown_vehicles(v, params)
    index = torch.cat([torch.zeros_like(order[:, :1]), order], 1)
    held = torch.cat([torch.ones_like(shown[:, :1]), shown], 1)
    columns = torch.stack([v.target_speed, v.timer, (v.target_lane - v.lane).to(v.x.dtype)], -1)
    hidden = columns.gather(1, index.unsqueeze(-1).expand(-1, -1, len(HIDDEN))).float()
    hidden = hidden * held.unsqueeze(-1)
    pad = params.observation.vehicles_count - hidden.shape[1]
    return torch.cat([hidden, hidden.new_zeros(len(hidden), pad, len(HIDDEN))], 1)


def label(args: argparse.Namespace) -> None:
    """``search_clone_scale.py label``'s labels, with :func:`hidden_rows` of each state."""
    cfg = _env_of(args.tail)
    params = tensor_params(str(cfg.scenario), OmegaConf.to_container(cfg.config))
    labels = label_range(
        args, args.seed, args.worlds, extra=lambda states: {"hidden": hidden_rows(states, params)}
    )
    torch.save(labels, args.out)


def _inputs(
    labels: dict[str, torch.Tensor], layout: KinematicsLayout
) -> dict[str, tuple[str, torch.Tensor, KinematicsLayout]]:
    # The three tables a fit reads: a file name, the table, the layout its trunk reads.
    obs, hidden = labels["observation"], labels["hidden"]
    wider = dataclasses.replace(layout, features=layout.features + HIDDEN)
    ego = torch.cat([hidden[:, :1], torch.zeros_like(hidden[:, 1:])], 1)
    return {
        "the observation": ("observation", obs, layout),
        "+ the ego's hidden state": ("ego_hidden", torch.cat([obs, ego], -1), wider),
        "+ every shown vehicle's hidden state": (
            "every_hidden",
            torch.cat([obs, hidden], -1),
            wider,
        ),
    }


def fit(args: argparse.Namespace) -> None:
    """The three fits (the module's docstring), then the first one's calibration."""
    torch.set_num_threads(args.threads)
    labels = torch.load(args.labels)
    scores, crashed = labels["scores"], labels["crashed"]
    test, fitted = held_out_split(len(scores))
    layout = make_layout(make_env(_env_of(args.tail)))
    epochs = _epochs(args, len(fitted))
    print(f"{len(scores)} states, {len(test)} held out\n")
    print("| input, aversion | states fitted | minutes | accuracy | regret | > 1 | crash error |")
    print("|---|---|---|---|---|---|---|")
    fits = []
    for name, (file, table, table_layout) in _inputs(labels, layout).items():
        start = time.perf_counter()
        x = table.flatten(1)
        net = new_net(args, table_layout, "attention", 1.0, x[fitted], scores.shape[1])
        tabled = {"observation": table, "scores": scores, "crashed": crashed}
        fit_net(net, tabled, fitted, epochs, 0.0, 1.0, cosine=True)
        minutes = (time.perf_counter() - start) / 60
        own = fitted[:20_000]
        with torch.no_grad():
            for aversion in args.aversions:
                net.aversion = aversion
                for where, rows in (("held out", test), ("fitted", own)):
                    figures = errors(net(x[rows]), scores[rows], crashed[rows])
                    how = f"{name}, aversion {aversion:g}, {where}"
                    print(_row(how, len(fitted), minutes, figures), flush=True)
        if args.out:
            torch.save(net, f"{args.out}/{file}.pt")
        fits.append((net, x))
    net, x = fits[0]  # the observation's fit
    calibration(net, x[test], scores[test], crashed[test], args.act_aversion)


@torch.no_grad()
def calibration(
    net: CloneNet, x: torch.Tensor, scores: torch.Tensor, crashed: torch.Tensor, aversion: float
) -> None:
    """The crash head's chance against the flags' frequency, and its chance for the
    chosen action at the states where ``net`` errs into a crash at ``aversion``."""
    _, crash = net.heads(x)
    p = crash.sigmoid()
    print("\n| the head's chance | actions | mean chance | crash frequency |\n|---|---|---|---|")
    edges = (0.0, 0.001, 0.01, 0.03, 0.1, 0.3, 0.7, 1.0001)
    for low, high in zip(edges, edges[1:], strict=False):
        bin_ = (p >= low) & (p < high)
        mean, freq = float(p[bin_].mean()), float(crashed[bin_].float().mean())
        print(f"| {low:g} to {min(high, 1):g} | {int(bin_.sum())} | {mean:.4f} | {freq:.4f} |")
    net.aversion = aversion
    chosen = net(x).argmax(-1, keepdim=True)
    wrong = crashed.gather(1, chosen).squeeze(-1) & ~crashed.all(-1)
    at = p.gather(1, chosen).squeeze(-1)[wrong]
    quartiles = torch.quantile(at, torch.tensor([0.25, 0.5, 0.75])).tolist() if len(at) else []
    print(
        f"\nat aversion {aversion:g} the fit errs into a crash on {int(wrong.sum())} of "
        f"{len(x)} states; the head's chance for the chosen action there, quartiles: "
        + ", ".join(f"{q:.3f}" for q in quartiles)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["label", "fit"])
    parser.add_argument("--tail", required=True, help="the run whose search made the labels")
    parser.add_argument("--labels", help="fit: a file that label wrote")
    parser.add_argument("--out", help="label: the file; fit: a folder for the fits")
    parser.add_argument("--worlds", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=100_000)
    parser.add_argument("--chunk", type=int, default=1000)
    parser.add_argument("--epsilon", type=float, default=0.3)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--native", action="store_true", help="label on the C++ substeps")
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--embed", type=int, default=64, help="the vehicles' embeddings")
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--max-steps", type=int, default=20_000, help="updates a fit at most")
    parser.add_argument("--aversions", type=float, nargs="+", default=[30.0, 100.0, 300.0])
    parser.add_argument("--act-aversion", type=float, default=100.0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    {"label": label, "fit": fit}[args.stage](args)


if __name__ == "__main__":
    main()
