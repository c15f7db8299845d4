"""How much of the planner's label does the observation decide? A fit ablation over inputs.

    python benchmarks/lab/label_inputs.py --scenario roundabout-v0 [--tail idle]
        [--worlds 1000] [--epsilon 0.3] [--horizon 8] [--seed 70000]
    python benchmarks/lab/label_inputs.py --tail runs/<name>/last.pt   # its own scenario
    python benchmarks/lab/label_inputs.py --scenario merge-v0 --tail slower --horizon 30 \
        --worlds 2000 --observation-only --drive 1000 --loss regret \
        --ranges '{"x": [-400, 400], "y": [-8, 8], "vx": [-80, 80], "vy": [-80, 80]}'

The lookahead planner (every action tried, then ``--horizon - 1`` steps of the scripted
``--tail`` policy or of a trained run's greedy actions, rows of the tensor simulator)
drives ``--worlds`` episodes from highway-env's starts of ``--seed, --seed + 1, ...``,
with a random action instead of its own on a fraction ``--epsilon`` of the steps so that
the states spread. At every state
it labels every action with its branch return. Then one MLP (two hidden layers of 256,
tanh; inputs standardised; 80% of the states to fit, 20% held out) fits the best set of
actions (cross-entropy to the uniform distribution over the actions tied with the
best), from three inputs:

- the observation the learner sees (highway-env's Kinematics table);
- the observation and the kinematics the table leaves out (every vehicle's heading,
  speed, speed set-point, steering, acceleration, lane-change timer, lane and target
  lane, from the simulator's state);
- all of that and what no observation shows: each vehicle's driving style (IDM's
  exponent ``delta``, drawn per vehicle at reset) and, on the roundabout, its planned
  route (destination and next leg).

and the observation alone from a quarter and a half of the fitted states. It prints
each fit's accuracy on the fitted and the held-out states (its argmax in the best
set) and the held-out regret (best return less the return of the fit's argmax), with
the share of held-out states where it exceeds 1, about what a crash forfeits within the
horizon. If the hidden inputs closed the held-out gap, the labels would depend on what
the learner cannot see; if more states close it, the fit is short of data.

``--observation-only`` fits the observation alone, from all the fitted states; ``--drive
N`` then drives that fit greedily over ``N`` tensor-simulator episodes from highway-env's
starts of seeds 40000.., beside the policy the search is over on the same episodes: what
a network distilled from the search drives like.
``--loss regret`` fits the expected regret instead of the best set (see :func:`fit`), and
``--ranges`` sets the observation's ``features_range`` (merge-v0's default hides the
ego's x beyond 200 m). ``--from-run`` fits the run's own network from its trained
weights instead of a fresh MLP (one round of expert iteration on the planner's labels);
with ``--keep-below R`` only the states where the run's own action loses more than ``R``
to the best are relabelled, the others keep the run's distribution as their target.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from omegaconf import DictConfig, OmegaConf
from search_labels import branch_outcomes
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.batched_search import highway_starts
from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.objectives.regret_fit import ANCHOR
from torchrl_grpo.training import make_env
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.env_builder import make_layout
from torchrl_grpo.training.evaluation import baseline_policy
from torchrl_grpo.training.pretrained import load_run_policy
from torchrl_grpo.training.results import compare_paired
from torchrl_grpo.training.transfer import evaluate_on_tensor

warnings.filterwarnings("ignore")
CONF_ENV = Path(__file__).resolve().parents[2] / "conf" / "env"


def searched_policy(
    scenario: str, tail: str, config: dict | None = None
) -> tuple[DictConfig, int, nn.Module]:
    """The env config, its number of actions and the greedy policy the search is over.

    ``tail``: a scripted policy's name (on ``scenario``, with the highway-env overrides
    ``config``) or a run's checkpoint (on its own scenario and config).
    """
    if tail.endswith(".pt"):
        cfg = OmegaConf.create(load_checkpoint(tail)["config"])["env"]
        highway = make_env(cfg)
        base = DeterministicActor(load_run_policy(tail, cfg, highway))
    else:
        cfg = _env_config(scenario)
        cfg.config = config or {}
        highway = make_env(cfg)
        base = baseline_policy(tail, make_layout(highway), int(highway.action_spec.n))
    return cfg, int(highway.action_spec.n), base


@torch.no_grad()
def labelled_states(
    scenario: str,
    tail: str,
    worlds: int,
    epsilon: float,
    horizon: int,
    seed: int,
    config: dict | None = None,
    keep_states: bool = True,
    native: bool = False,
    behaviour: nn.Module | None = None,
) -> tuple[str, torch.Tensor, TensorDict | None, torch.Tensor, torch.Tensor]:
    """The scenario, the planner's states (observations, full states), each action's score
    and whether its branch crashed.

    ``keep_states=False`` keeps no full state (``None`` in their place): a large labelling
    run holds only what a fit of the observation needs. ``native``: the C++ substeps
    (``TensorHighwayEnv(native=True)``), for speed. ``behaviour``: the policy that drives
    between the random actions (default: the search itself), such as a fit of the search
    driving its own states (DAgger).
    """
    cfg, n_actions, base = searched_policy(scenario, tail, config)
    scenario, overrides = str(cfg.scenario), OmegaConf.to_container(cfg.config)
    planner = LookaheadPolicy(
        TensorHighwayEnv(scenario, overrides, num_envs=n_actions * worlds, native=native),
        base,
        horizon,
    )
    env = TensorHighwayEnv(scenario, overrides, num_envs=worlds, return_state=True, native=native)
    td = highway_starts(env, list(range(seed, seed + worlds)))
    draws = torch.Generator().manual_seed(seed)
    live = torch.ones(worlds, dtype=torch.bool)
    observations, states, scores, crashes = [], [], [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        while live.any():
            score, crashed = branch_outcomes(planner, td)
            observations.append(td["observation"][live])
            if keep_states:
                states.append(td["state"][live])
            scores.append(score[live])
            crashes.append(crashed[live])
            explore = torch.rand(worlds, generator=draws) < epsilon
            random = torch.randint(0, n_actions, (worlds,), generator=draws)
            own = score.argmax(-1) if behaviour is None else behaviour(td.clone())["action"]
            td["action"] = torch.where(explore, random, own)
            out, td = env.step_and_maybe_reset(td)
            # A finished world is reset by the step: its later states are not this episode's.
            live &= ~out["next", "done"].reshape(-1)
    kept = torch.cat(states) if keep_states else None
    return scenario, torch.cat(observations), kept, torch.cat(scores).float(), torch.cat(crashes)


def _env_config(scenario: str) -> DictConfig:
    # The env group of conf/env/ that names the scenario: its episode cap ends the drives.
    for path in sorted(CONF_ENV.glob("*.yaml")):
        cfg = OmegaConf.load(path)
        if cfg.get("scenario") == scenario:
            return OmegaConf.create({k: v for k, v in cfg.items() if k != "defaults"})
    raise SystemExit(f"no conf/env/*.yaml has scenario {scenario}")


def _one_hot(codes: torch.Tensor) -> torch.Tensor:
    # [N, V] integer codes -> [N, V * distinct codes]
    return (codes.unsqueeze(-1) == torch.unique(codes)).float().flatten(1)


def inputs(observation: torch.Tensor, state: TensorDict) -> dict[str, torch.Tensor]:
    """The three inputs of the ablation, ``[N, features]`` each."""
    v = state["vehicles"]
    seen = observation.flatten(1).float()
    kinematics = [
        torch.cos(v["heading"]),
        torch.sin(v["heading"]),
        v["speed"],
        v["target_speed"],
        v["steering"],
        v["acceleration"],
        v["timer"],
    ]
    kinematics = torch.cat([seen, *(k.float() for k in kinematics)], -1)
    kinematics = torch.cat([kinematics, _one_hot(v["lane"]), _one_hot(v["target_lane"])], -1)
    hidden = [kinematics, v["delta"].float()]
    if "route" in state.keys():
        legs, head = state["route", "legs"], state["route", "head"]
        last = torch.where(legs >= 0, torch.arange(legs.shape[-1]), -1).amax(-1).clamp(min=0)
        destination = legs.gather(-1, last.unsqueeze(-1)).squeeze(-1)
        following = (head + 1).clamp(max=legs.shape[-1] - 1)
        hidden += [_one_hot(destination), _one_hot(legs.gather(-1, following[..., None])[..., 0])]
    return {
        "observation": seen,
        "+ kinematics the table leaves out": kinematics,
        "+ driving style and route (hidden)": torch.cat(hidden, -1),
    }


def fit(
    x: torch.Tensor,
    scores: torch.Tensor,
    train: torch.Tensor,
    test: torch.Tensor,
    epochs: int,
    net: nn.Module | None = None,
    keep_below: float | None = None,
    loss: str = "best-set",
    width: int = 256,
    danger: torch.Tensor | None = None,
    danger_weight: float = 0.0,
    seed: int = 0,
) -> tuple[dict[str, float], nn.Module]:
    """Fits the best set from ``x[train]``; accuracy and regret on ``train`` and ``test``.

    ``loss``: ``best-set``, the cross-entropy to the uniform distribution over the tied
    best actions; or ``regret``, the expected regret of the network's distribution
    (``sum_a pi(a) (max Q - Q(a))``) plus a tenth of that cross-entropy (``ANCHOR``, as
    in the group fit ``algo.group_fit_loss=regret``). The regret
    weighs each state by what a wrong action costs there; alone it settles on one action
    everywhere, since the actions the network gives no probability get no gradient.

    ``net``: the network to fit (default: a fresh MLP of two hidden layers of ``width``,
    standardisation included).
    ``keep_below``: where the network's own greedy action loses less than this to the
    best one, its target is its own distribution as it was before the fit (only the
    states where it loses more are corrected).
    ``danger``: ``[N, A]``, the actions whose branch crashes where another action's does
    not; the loss adds ``danger_weight`` times the probability the network gives them,
    an expected crash that weighs the states where one action crashes. ``seed``: the
    fresh network's initial weights and the order of the states.
    Returns the figures and the fitted network.
    """
    best = (scores >= scores.amax(-1, keepdim=True) - 1e-6).float()
    target = best / best.sum(-1, keepdim=True)
    if keep_below is not None:
        with torch.no_grad():
            own = net(x)
        regret = scores.amax(-1) - scores.gather(1, own.argmax(-1, keepdim=True)).squeeze(-1)
        keep = regret < keep_below
        target = torch.where(keep[:, None], own.softmax(-1), target)
        print(f"(corrected: {1 - float(keep[train].float().mean()):.1%} of the fitted states)")
    mean, std = x[train].mean(0), x[train].std(0) + 1e-6
    torch.manual_seed(seed)
    net = net or nn.Sequential(
        _Standardise(mean, std),
        nn.Linear(x.shape[1], width),
        nn.Tanh(),
        nn.Linear(width, width),
        nn.Tanh(),
        nn.Linear(width, scores.shape[1]),
    )
    optim = torch.optim.Adam(net.parameters(), lr=1e-3)
    order = torch.Generator().manual_seed(1 + seed)
    regret = scores.amax(-1, keepdim=True) - scores
    for _ in range(epochs):
        for rows in train[torch.randperm(len(train), generator=order)].split(256):
            log_p = net(x[rows]).log_softmax(-1)
            value = -(target[rows] * log_p).sum(-1).mean()
            if loss == "regret":
                value = (log_p.exp() * regret[rows]).sum(-1).mean() + ANCHOR * value
            if danger is not None:
                value = value + danger_weight * (log_p.exp() * danger[rows]).sum(-1).mean()
            optim.zero_grad()
            value.backward()
            optim.step()
    with torch.no_grad():
        chosen = net(x).argmax(-1, keepdim=True)
        hit = best.gather(1, chosen).squeeze(-1)
        regret = scores.amax(-1) - scores.gather(1, chosen).squeeze(-1)
    figures = {
        "fitted accuracy": float(hit[train].mean()),
        "held-out accuracy": float(hit[test].mean()),
        "held-out regret": float(regret[test].mean()),
        "held-out regret > 1": float((regret[test] > 1).float().mean()),
    }
    return figures, net


class _Standardise(nn.Module):
    def __init__(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class _RunLogits(nn.Module):
    """A run's actor as a network from the flat observation to its logits."""

    def __init__(self, actor: nn.Module, shape: torch.Size) -> None:
        super().__init__()
        self.actor, self.shape = actor, shape

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        td = TensorDict({"observation": x.reshape(-1, *self.shape)}, batch_size=[len(x)])
        return self.actor(td)["logits"]


class _Greedy(nn.Module):
    """The fitted network as a policy: the argmax of its logits over the flat observation."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, td: TensorDict) -> TensorDict:
        obs = td["observation"]
        logits = self.net(obs.reshape(*obs.shape[: td.batch_dims], -1).float())
        td["action"] = logits.argmax(-1)
        return td


def drive(
    scenario: str, tail: str, net: nn.Module | dict, episodes: int, config: dict | None = None
) -> None:
    """The fit's greedy episodes beside the searched policy's own, on the tensor simulator
    (``net`` a dict: each named fit over the same episodes, the policy driven once)."""
    fits = net if isinstance(net, dict) else {"the fit of its search, greedy": net}
    cfg, _, base_policy = searched_policy(scenario, tail, config)
    kw = {"episodes": episodes, "seed": 40_000}
    base = evaluate_on_tensor(cfg, base_policy, name=f"{tail}, greedy", **kw)
    fitted = [evaluate_on_tensor(cfg, _Greedy(f), name=n, **kw) for n, f in fits.items()]
    for res in (base, *fitted):
        s, paired = res.summary(), "" if res is base else f"; {compare_paired(res, base)}"
        print(f"- {res.name}: {s['return']:.2f} / {s['crash_rate']:.2%} over {episodes}{paired}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="roundabout-v0")
    parser.add_argument(
        "--tail", default="idle", help="after the first action: a scripted policy or a run's .pt"
    )
    parser.add_argument("--worlds", type=int, default=1000)
    parser.add_argument("--epsilon", type=float, default=0.3)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--seed", type=int, default=70_000)
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--observation-only", action="store_true")
    parser.add_argument(
        "--from-run", action="store_true", help="fit the --tail run's own network, from its weights"
    )
    parser.add_argument("--drive", type=int, default=0, help="episodes the fit drives")
    parser.add_argument(
        "--keep-below",
        type=float,
        default=None,
        help="with --from-run: correct only the states where the run's action loses this much",
    )
    parser.add_argument("--loss", default="best-set", choices=["best-set", "regret"])
    parser.add_argument(
        "--ranges",
        type=json.loads,
        default=None,
        help='the observation\'s features_range, JSON: {"x": [-400, 400], ...}',
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = None
    if args.ranges:
        config = {"observation": {"type": "Kinematics", "features_range": args.ranges}}
    scenario, observation, state, scores, _ = labelled_states(
        args.scenario, args.tail, args.worlds, args.epsilon, args.horizon, args.seed, config
    )
    n = len(scores)
    best = scores >= scores.amax(-1, keepdim=True) - 1e-6
    split = torch.randperm(n, generator=torch.Generator().manual_seed(args.seed))
    train, test = split[: int(0.8 * n)], split[int(0.8 * n) :]
    print(
        f"{scenario}: {n} states of {args.worlds} episodes, search {args.horizon} over "
        f"{args.tail}; one best action on {float((best.sum(-1) == 1).float().mean()):.1%}, "
        f"mean best set {float(best.sum(-1).float().mean()):.2f} actions"
    )
    print("\n| input | states fitted | fitted acc. | held-out acc. | held-out regret | > 1 |")
    print("|---|---|---|---|---|---|")
    rows = [(name, x, train) for name, x in inputs(observation, state).items()]
    if args.observation_only:
        rows = rows[:1]
    else:
        rows += [("observation", rows[0][1], train[: len(train) // k]) for k in (4, 2)]
    for name, x, fitted in rows:
        start = None
        if args.from_run and name == "observation":
            cfg = OmegaConf.create(load_checkpoint(args.tail)["config"])["env"]
            actor = load_run_policy(args.tail, cfg, make_env(cfg))
            start = _RunLogits(actor, observation.shape[1:])
        keep = args.keep_below if start is not None else None
        r, net = fit(x, scores, fitted, test, args.epochs, start, keep, args.loss)
        print(
            f"| {name} | {len(fitted)} | {r['fitted accuracy']:.3f} | "
            f"{r['held-out accuracy']:.3f} | {r['held-out regret']:.3f} | "
            f"{r['held-out regret > 1']:.1%} |"
        )
        if args.drive and fitted is train and name == "observation":
            print()
            drive(scenario, args.tail, net, args.drive, config)


if __name__ == "__main__":
    main()
