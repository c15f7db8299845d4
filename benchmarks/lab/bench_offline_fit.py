"""What a network learns from the planner's exact action comparisons, offline, at scale.

The groups of ``algo=grpo_branch`` (every first action enumerated, the rule policy on
the tails) score ``Q_rule(s, a)`` for the five actions of a root: exactly what the
lookahead planner compares. This benchmark separates what a learner does with those
comparisons from how training collects them:

``collect`` drives ``--episodes`` worlds of the tensor simulator at once with a
behaviour policy (the planner, or a checkpoint's greedy policy, with ``--noise``
random actions), and at every step scores all five actions of every world (the
planner's branches, rows of one batched rollout): the ``H``-step return of each and
whether it crashes. It saves the states (so that observations of any Kinematics
config can be computed from them), the scores and the crash flags.

``fit`` trains a policy network on saved data with one of the losses below, then
reports, on held-out states, how often its greedy choice is a crashing action where
another does not crash, and drives 1,000 greedy episodes on the tensor simulator from
highway-env's starting worlds (the transfer gap is below 1e-6, so these are
highway-env's figures):

- ``ce``: cross-entropy to ``softmax(Q / tau)`` (``algo.group_fit_loss=cross_entropy``);
- ``reg``: the centred logits times ``tau`` regress the centred ``Q``
  (``algo.group_fit_loss=regression``).

    python benchmarks/lab/bench_offline_fit.py collect --episodes 2000 --out /tmp/labels.pt
    python benchmarks/lab/bench_offline_fit.py fit --data /tmp/labels.pt --model scene --loss ce
"""

from __future__ import annotations

import argparse
import logging
import math
import time

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_grpo.branching import branch_rollout
from torchrl_grpo.branching.keys import MASK
from torchrl_grpo.branching.lookahead import ActionThenBase
from torchrl_grpo.envs import TensorHighwayEnv, tensor_params
from torchrl_grpo.experimental.grpo_lab import GRPOLabModelConfig  # the lab's kinds too
from torchrl_grpo.modules import CrashHead, make_scripted_policy
from torchrl_grpo.sim.observation import observe
from torchrl_grpo.sim.state import Vehicles
from torchrl_grpo.training import make_env
from torchrl_grpo.training.env_builder import make_layout
from torchrl_grpo.training.model_builder import make_policy
from torchrl_grpo.training.transfer import evaluate_on_tensor

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_offline_fit")
SCENARIO = "highway-fast-v0"
N_ACTIONS = 5


def score_actions(plan_env, tail, state: TensorDict, horizon: int):
    """Every action's ``horizon``-step return (then ``tail``) and whether it crashes."""
    n = state.shape[0]
    roots = TensorDict(state=state, root_step=torch.zeros(n, dtype=torch.long), batch_size=[n])
    data = branch_rollout(plan_env, tail, roots.clone(), N_ACTIONS, horizon)
    mask = data.get(MASK)
    reward = data.get(("next", "reward")).reshape(mask.shape).double()
    crashed = data.get(("next", "crashed")).reshape(mask.shape) & mask
    return torch.where(mask, reward, 0.0).sum(-1), crashed.any(-1)


def collect(args) -> None:
    torch.set_num_threads(args.threads)
    env = TensorHighwayEnv(SCENARIO, num_envs=args.episodes, seed=args.seed, return_state=True)
    plan_env = TensorHighwayEnv(SCENARIO, num_envs=N_ACTIONS * args.episodes, seed=1)
    layout = make_layout(make_env(OmegaConf.create({"scenario": SCENARIO, "config": {}})))
    tail = ActionThenBase(make_scripted_policy("rule", layout))
    behaviour = None
    if args.checkpoint:
        from bench_crash_rates import trained

        _, behaviour = trained(args.checkpoint)
    gen = torch.Generator().manual_seed(args.seed)
    td = env.reset()
    states, scores, crashes, steps = [], [], [], []
    t0 = time.perf_counter()
    for t in range(args.steps):
        q, crash = score_actions(plan_env, tail, td.get("state"), args.horizon)
        states.append(td.get("state").get("vehicles").clone())
        scores.append(q.float())
        crashes.append(crash)
        steps.append(td.get("state").get("steps").clone())
        if behaviour is None:
            action = q.argmax(-1)
        else:
            with torch.no_grad():
                action = behaviour(td.select("observation").clone()).get("logits").argmax(-1)
        noise = torch.rand(args.episodes, generator=gen) < args.noise
        random = torch.randint(N_ACTIONS, (args.episodes,), generator=gen)
        td.set("action", torch.where(noise, random, action))
        _, td = env.step_and_maybe_reset(td)
        log.info("step %d: %.0f s", t, time.perf_counter() - t0)
    vehicles = torch.cat(states)
    torch.save(
        {
            "vehicles": {k: v for k, v in vehicles.items()},
            "q": torch.cat(scores),
            "crash": torch.cat(crashes),
            "steps": torch.cat(steps),
            "horizon": args.horizon,
        },
        args.out,
    )
    log.info("%d states saved to %s", vehicles.shape[0], args.out)


def observations(data: dict, obs_config: dict | None) -> torch.Tensor:
    """The Kinematics tables of the saved states under ``obs_config``."""
    config = {} if obs_config is None else {"observation": obs_config}
    params = tensor_params(SCENARIO, config)
    table = data["vehicles"]
    vehicles = Vehicles(**{k: table[k] for k in Vehicles._fields})
    return observe(vehicles, params).float()


def split(n: int, max_states: int | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Held-out (the same tenth of the states for every fit) and training state indices."""
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    return perm[: n // 10], perm[n // 10 :][:max_states]


def crashing_picks(crash: torch.Tensor, greedy: torch.Tensor) -> float:
    """The share of danger states (some action crashes, not all) where ``greedy`` crashes."""
    danger = crash.any(-1) & ~crash.all(-1)
    picked = crash.gather(-1, greedy[:, None]).squeeze(-1)
    return float(picked[danger].float().mean())


def fit_logits(logits_of, params, centred: torch.Tensor, train: torch.Tensor, args) -> None:
    """``args.updates`` Adam steps of the ``args.loss`` fit of ``logits_of(rows)`` to ``centred``.

    ``ce``: cross-entropy to ``softmax(Q / tau)``; ``reg``: ``tau`` times the centred
    logits regress the centred ``Q``.
    """
    params = list(params)
    opt = torch.optim.Adam(params, lr=args.lr)
    t0 = time.perf_counter()
    for step in range(args.updates):
        idx = train[torch.randint(len(train), (args.batch,))]
        logits = logits_of(idx)
        if args.loss == "ce":
            target = torch.softmax(centred[idx] / args.tau, -1)
            loss = -(target * torch.log_softmax(logits, -1)).sum(-1).mean()
        else:
            estimate = args.tau * (logits - logits.mean(-1, keepdim=True))
            loss = (estimate - centred[idx]).pow(2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        if step % 2000 == 0:
            spent = time.perf_counter() - t0
            log.info("update %d: loss %.4f (%.0f s)", step, float(loss.detach()), spent)


def fit(args) -> None:
    torch.set_num_threads(args.threads)
    data = torch.load(args.data)
    if args.privileged:
        return fit_privileged(args, data)
    if args.loss == "shield":
        return fit_shield(args, data)
    obs_config = None
    if args.vehicles != 5 or args.see_behind:
        obs_config = {
            "type": "Kinematics",
            "vehicles_count": args.vehicles,
            "see_behind": args.see_behind,
        }
    env_cfg = OmegaConf.create(
        {
            "scenario": SCENARIO,
            "config": {} if obs_config is None else {"observation": obs_config},
            "max_episode_steps": 40,
        }
    )
    obs = observations(data, obs_config)
    crash = data["crash"]
    # The training reward's crash penalty: a crashing branch pays it on top of what it forfeits.
    q = data["q"] - args.crash_penalty * crash.float()
    held, train = split(q.shape[0], args.max_states)
    torch.manual_seed(args.seed)
    policy = make_policy(
        OmegaConf.structured(GRPOLabModelConfig(kind=args.model, num_cells=args.cells)),
        make_env(env_cfg),
    )

    def logits_of(rows: torch.Tensor) -> torch.Tensor:
        return policy(TensorDict(observation=obs[rows], batch_size=[len(rows)]))["logits"]

    fit_logits(logits_of, policy.parameters(), q - q.mean(-1, keepdim=True), train, args)
    for name, rows in (("held-out", held), ("training", train[: len(held)])):
        with torch.no_grad():
            greedy = logits_of(rows).argmax(-1)
        danger = crash[rows].any(-1) & ~crash[rows].all(-1)
        q_plain = data["q"][rows]
        regret = q_plain.max(-1).values - q_plain.gather(-1, greedy[:, None]).squeeze(-1)
        log.info(
            "%s: %d states, %.1f%% danger; greedy picks a crashing action in %.2f%% of the "
            "danger states; mean regret %.3f",
            name,
            len(rows),
            100 * float(danger.float().mean()),
            100 * crashing_picks(crash[rows], greedy),
            float(regret.mean()),
        )
    res = evaluate_on_tensor(env_cfg, policy, episodes=args.episodes, seed=30_000, name="fit")
    rate = sum(res.crashed) / len(res.crashed)
    ret = torch.tensor(res.returns, dtype=torch.float64)
    print(
        f"{args.model} {args.loss} tau={args.tau} vehicles={args.vehicles} "
        f"see_behind={args.see_behind} penalty={args.crash_penalty} states={len(train)} "
        f"updates={args.updates} cells={args.cells}: return {ret.mean():.2f}, crash rate "
        f"{100 * rate:.1f}% ± {100 * math.sqrt(max(rate * (1 - rate), 1e-12) / len(ret)):.1f} "
        f"({len(ret)} episodes)"
    )


def fit_privileged(args, data: dict) -> None:
    """``fit`` with an MLP over :func:`privileged_features` (the whole vehicle table)."""
    from privileged_features import PrivilegedPolicy, privileged_features
    from torchrl.modules import MLP

    x = privileged_features(data["vehicles"])
    crash = data["crash"]
    q = data["q"] - args.crash_penalty * crash.float()
    held, train = split(q.shape[0], args.max_states)
    torch.manual_seed(args.seed)
    net = MLP(
        in_features=x.shape[-1],
        out_features=N_ACTIONS,
        num_cells=args.cells,
        activation_class=torch.nn.Tanh,
    )
    centred = q - q.mean(-1, keepdim=True)
    fit_logits(lambda rows: net(x[rows]), net.parameters(), centred, train, args)
    for name, rows in (("held-out", held), ("training", train[: len(held)])):
        with torch.no_grad():
            greedy = net(x[rows]).argmax(-1)
        log.info(
            "%s: greedy picks a crashing action in %.2f%% of the danger states",
            name,
            100 * crashing_picks(crash[rows], greedy),
        )
    env_cfg = OmegaConf.create({"scenario": SCENARIO, "config": {}, "max_episode_steps": 40})
    res = evaluate_on_tensor(
        env_cfg, PrivilegedPolicy(net), episodes=args.episodes, seed=30_000, return_state=True
    )
    rate = sum(res.crashed) / len(res.crashed)
    ret = torch.tensor(res.returns, dtype=torch.float64)
    print(
        f"privileged {args.loss} tau={args.tau} penalty={args.crash_penalty} states={len(train)}: "
        f"return {ret.mean():.2f}, crash rate {100 * rate:.1f}% ({len(ret)} episodes)"
    )


class ShieldPolicy(torch.nn.Module):
    """Greedy over the Q estimates of actions whose crash probability is below ``threshold``.

    With ``aversion > 0`` no mask: greedy over ``Q + aversion * log(1 - p_crash)``.
    """

    def __init__(self, net: torch.nn.Module, threshold: float, aversion: float = 0.0) -> None:
        super().__init__()
        self.net, self.threshold, self.aversion = net, threshold, aversion

    def forward(self, td: TensorDict) -> TensorDict:
        observation = td.get("observation")
        if self.aversion > 0:
            # As model.crash_aversion acts in training: Q + aversion * log(1 - p_crash).
            logits = CrashHead(self.net, N_ACTIONS, self.aversion)(observation)
            return td.set("action", logits.argmax(-1))
        out = self.net(observation)
        q, risk = out[..., :N_ACTIONS], torch.sigmoid(out[..., N_ACTIONS:])
        safe = risk < self.threshold
        # Where every action looks unsafe, the least risky one.
        masked = torch.where(safe, q, torch.full_like(q, -float("inf")))
        action = torch.where(safe.any(-1), masked.argmax(-1), risk.argmin(-1))
        return td.set("action", action)


def fit_shield(args, data: dict) -> None:
    """Q estimates (squared error) and crash probabilities (cross-entropy) of every action."""
    from torchrl_grpo.modules import KinematicsLayout, SceneMLP

    obs = observations(data, None)
    crash = data["crash"]
    q = data["q"]
    centred = q - q.mean(-1, keepdim=True)
    held, train = split(q.shape[0], args.max_states)
    torch.manual_seed(args.seed)
    net = SceneMLP(KinematicsLayout(), 2 * N_ACTIONS, num_cells=args.cells)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    for step in range(args.updates):
        idx = train[torch.randint(len(train), (args.batch,))]
        out = net(obs[idx])
        est = out[:, :N_ACTIONS]
        reg = (est - est.mean(-1, keepdim=True) - centred[idx]).pow(2).sum(-1).mean()
        bce = (
            torch.nn.functional.binary_cross_entropy_with_logits(
                out[:, N_ACTIONS:], crash[idx].float(), reduction="none"
            )
            .sum(-1)
            .mean()
        )
        loss = reg + args.shield_coeff * bce
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        if step % 2000 == 0:
            log.info("update %d: reg %.4f bce %.4f", step, float(reg), float(bce))
    env_cfg = OmegaConf.create({"scenario": SCENARIO, "config": {}, "max_episode_steps": 40})
    variants = [(t, 0.0) for t in args.thresholds] + [(1.1, a) for a in args.aversions]
    for threshold, aversion in variants:
        policy = ShieldPolicy(net, threshold, aversion)
        with torch.no_grad():
            greedy = policy(TensorDict(observation=obs[held], batch_size=[len(held)]))["action"]
        res = evaluate_on_tensor(env_cfg, policy, episodes=args.episodes, seed=30_000)
        rate = sum(res.crashed) / len(res.crashed)
        ret = torch.tensor(res.returns, dtype=torch.float64)
        print(
            f"shield threshold={threshold} aversion={aversion} coeff={args.shield_coeff}: "
            "held-out crash picks "
            f"{100 * crashing_picks(crash[held], greedy):.2f}% of danger states; return "
            f"{ret.mean():.2f}, crash rate {100 * rate:.1f}% ({len(ret)} episodes)"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--episodes", type=int, default=1000)
    c.add_argument("--steps", type=int, default=30)
    c.add_argument("--horizon", type=int, default=8)
    c.add_argument("--noise", type=float, default=0.2)
    c.add_argument("--checkpoint", default=None, help="behaviour: a run's greedy policy")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--threads", type=int, default=1)
    c.add_argument("--out", required=True)
    f = sub.add_parser("fit")
    f.add_argument("--data", required=True)
    f.add_argument("--model", default="scene")
    f.add_argument("--cells", type=int, nargs="+", default=[256, 256])
    f.add_argument("--loss", choices=["ce", "reg", "shield"], default="ce")
    f.add_argument("--shield-coeff", type=float, default=1.0)
    f.add_argument("--thresholds", type=float, nargs="+", default=[1.1, 0.5, 0.2, 0.1, 0.05])
    f.add_argument("--aversions", type=float, nargs="+", default=[1.0, 3.0, 10.0])
    f.add_argument("--tau", type=float, default=0.1)
    f.add_argument("--crash-penalty", type=float, default=0.0)
    f.add_argument("--max-states", type=int, default=None, help="train on this many states")
    f.add_argument("--vehicles", type=int, default=5)
    f.add_argument("--see-behind", action="store_true")
    f.add_argument("--privileged", action="store_true", help="features of the whole state")
    f.add_argument("--updates", type=int, default=20000)
    f.add_argument("--batch", type=int, default=1024)
    f.add_argument("--lr", type=float, default=5e-4)
    f.add_argument("--episodes", type=int, default=1000)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    collect(args) if args.cmd == "collect" else fit(args)


if __name__ == "__main__":
    main()
