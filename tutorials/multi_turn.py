# ruff: noqa: T201
"""Multi-turn branching: branch, keep the best branch, continue from its end, repeat.

It teaches :func:`torchrl_grpo.branching.multi_turn_rollout` on highway-fast-v0:

* at a decision point, G branches of a stochastic policy (here a randomly initialised
  MLP actor, the policy GRPO training starts from) run H steps each, all from bitwise
  the same simulator state;
* the branch with the highest return is selected
  (:func:`~torchrl_grpo.branching.select_branches` with ``"best"``) and the episode
  continues from that branch's final state, bit for bit; this repeats until the
  episode ends;
* :class:`~torchrl_grpo.branching.MultiTurnResult` holds every group (``groups``,
  ``[N, G, H]``, with ``selected``) and ``trunk(e)``, the steps the episode took;
* the stitched episode is a real episode: replaying its actions open-loop from the start
  gives the same rewards bit for bit;
* and what select-and-continue buys: its episode return next to rollouts of the same
  policy from the same start without branching
  (:func:`~torchrl_grpo.branching.branch_rollout` with a horizon of a whole episode).

Run it::

    python tutorials/multi_turn.py           # about 20 s on 2 cores
    python tutorials/multi_turn.py --quick   # the short form the tests run

Pictures (in ``--out``, default ``outputs/tutorials/multi_turn``): ``trunk_and_branches.png``,
``branch_returns.png`` and ``episode_return.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display needed

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict, TensorDictBase  # noqa: E402

from torchrl_grpo.branching import (  # noqa: E402
    MultiTurnResult,
    branch_rollout,
    make_branch_env,
    multi_turn_rollout,
    reset_roots,
    shutdown_env,
)
from torchrl_grpo.envs.core.snapshot_batched import local_worker_env  # noqa: E402
from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor  # noqa: E402

NAME = "multi_turn"


def replay(env, root_state: TensorDictBase, actions: torch.Tensor) -> torch.Tensor:
    """Rewards of ``actions`` played open-loop from ``root_state`` on a plain env."""
    env.reset(TensorDict(state=root_state.clone()), set_state=True)
    rewards = [env.step(TensorDict(action=a.clone()))["next", "reward"] for a in actions]
    return torch.stack(rewards)


def branch_paths(groups: TensorDictBase, n: int) -> list[tuple[np.ndarray, bool]]:
    """Ego x-y path and crash flag of every branch of group ``n``."""
    out = []
    for g in range(groups.shape[1]):
        branch = groups[n, g]
        valid = branch["mask"]
        start = branch["ego_position"][:1].double().numpy()
        after = branch["next", "ego_position"][valid].double().numpy()
        crashed = bool(branch["next", "crashed"][valid].any())
        out.append((np.concatenate([start, after]), crashed))
    return out


# ---------------------------------------------------------------------------- plots
def plot_trunk(res: MultiTurnResult, trunk_xy: np.ndarray, lanes: int, path: Path) -> None:
    """The episode's path (the chosen branches) with every group's branches around it."""
    fig, ax = plt.subplots(figsize=(13, 4))
    for y in np.arange(lanes + 1) * 4.0 - 2.0:  # lane boundaries (4 m lanes)
        ax.axhline(y, color="0.88", lw=1, ls="-" if y in (-2.0, lanes * 4.0 - 2.0) else "--")
    cmap = plt.get_cmap("tab10")
    for n in range(res.groups.shape[0]):
        color = cmap(n % 10)
        for g, (xy, crashed) in enumerate(branch_paths(res.groups, n)):
            if g == int(res.selected[n]):
                continue  # drawn as part of the trunk
            ax.plot(xy[:, 0], xy[:, 1], color=color, lw=1, alpha=0.6)
            ax.plot(*xy[-1], "x" if crashed else ".", color=color, ms=7 if crashed else 4)
        start = res.groups[n, 0, 0]["ego_position"].double().numpy()
        ax.plot(*start, "o", color=color, ms=7, mec="k", zorder=5)
        ax.annotate(
            f"t={int(res.groups[n, 0, 0]['root_step'])}",
            start,
            xytext=(0, 8),
            textcoords="offset points",
            ha="center",
            fontsize=7,
        )
    ax.plot(trunk_xy[:, 0], trunk_xy[:, 1], "k-", lw=2.5, label="trunk (chosen branches)")
    ax.plot([], [], "o", color="0.6", mec="k", label="decision point (colour: its branches)")
    ax.plot([], [], "x", color="0.3", label="branch crashed")
    ax.invert_yaxis()  # highway-env's y points to the right-hand side of the road
    ax.set(
        xlabel="x (m)", ylabel="y (m)", title="the trunk and the branches at every decision point"
    )
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_branch_returns(res: MultiTurnResult, path: Path) -> None:
    """Every branch's return per decision point; the chosen one starred."""
    returns = res.groups["branch_return"][:, :, 0, 0].double().numpy()  # [N, G]
    steps = res.groups["root_step"][:, 0, 0].numpy()
    n, g = returns.shape
    crashed = (res.groups["next", "crashed"].squeeze(-1) & res.groups["mask"]).any(-1).numpy()
    fig, ax = plt.subplots(figsize=(9, 4.5))
    rng = np.random.default_rng(0)  # jitter only
    for i in range(n):
        x = steps[i] + rng.uniform(-0.6, 0.6, g)
        ok = ~crashed[i]
        ax.plot(x[ok], returns[i, ok], "o", color="tab:blue", alpha=0.6, ms=5)
        ax.plot(x[~ok], returns[i, ~ok], "x", color="tab:red", ms=7, mew=2)
        ax.plot(steps[i], returns[i, int(res.selected[i])], "*", color="gold", mec="k", ms=16)
    ax.plot([], [], "o", color="tab:blue", label="branch")
    ax.plot([], [], "x", color="tab:red", label="branch that crashed")
    ax.plot([], [], "*", color="gold", mec="k", ms=12, label="selected (best)")
    ax.set(
        xlabel="decision point (episode step)",
        ylabel=f"branch return ({res.groups.shape[2]} steps)",
        title=f"return of each of the {g} branches per decision point",
    )
    ax.set_xticks(steps)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_episode_return(
    trunk_rewards: np.ndarray, baseline: TensorDictBase, decision_steps: np.ndarray, path: Path
) -> None:
    """Running return of the multi-turn episode and of the no-branching rollouts."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for k in range(baseline.shape[1]):
        valid = baseline["mask"][0, k]
        r = baseline["next", "reward"][0, k][valid].reshape(-1).double().numpy()
        label = "no branching (same policy, same start)" if k == 0 else None
        ax.plot(np.arange(1, len(r) + 1), np.cumsum(r), color="0.6", lw=1, label=label)
        if bool(baseline["next", "crashed"][0, k][valid].any()):
            ax.plot(len(r), r.sum(), "x", color="tab:red", ms=7, mew=2)
    t = np.arange(1, len(trunk_rewards) + 1)
    ax.plot(t, np.cumsum(trunk_rewards), "k-", lw=2.5, label="multi-turn, best branch")
    for s in decision_steps:
        ax.axvline(s, color="tab:blue", lw=0.6, alpha=0.4)
    ax.plot([], [], "x", color="tab:red", label="crash")
    ax.set(
        xlabel="episode step (blue lines: decision points)",
        ylabel="return so far",
        title="episode return: select-and-continue vs no branching",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="highway-fast-v0", help="highway-env scenario")
    p.add_argument("--seed", type=int, default=0, help="episode and policy seed")
    p.add_argument("--group-size", type=int, default=None, help="G, branches per decision")
    p.add_argument("--horizon", type=int, default=None, help="H, steps per branch")
    p.add_argument("--duration", type=int, default=None, help="episode length (s) override")
    p.add_argument(
        "--backend", default="single", choices=["single", "serial", "parallel"], help="workers"
    )
    p.add_argument("--workers", type=int, default=2, help="W for serial / parallel")
    p.add_argument("--quick", action="store_true", help="short form (tests): short episode")
    p.add_argument("--out", type=Path, default=Path("outputs/tutorials") / NAME)
    args = p.parse_args(argv)
    args.group_size = args.group_size or (3 if args.quick else 8)
    args.horizon = args.horizon or (4 if args.quick else 5)
    if args.duration is None and args.quick:
        args.duration = 8
    return args


def main(argv: list[str] | None = None) -> None:
    """Branch, select, continue to the episode's end; compare with no branching."""
    args = parse_args(argv)
    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)  # the actor's initial weights and its action samples
    torch.set_num_threads(1)  # leave the cores to the simulators
    actor = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
    config = {} if args.duration is None else {"duration": args.duration}
    workers = 1 if args.backend == "single" else args.workers
    env = make_branch_env(
        args.scenario, workers, config=config, backend=args.backend, mp_start_method="fork"
    )
    try:
        plain = local_worker_env(env)  # a plain HighwayEnv built like the workers
        env_config = plain.config
        max_steps = int(env_config["duration"] * env_config["policy_frequency"])
        roots = reset_roots(env, 1, seed=args.seed)  # one episode start
        print(
            f"{args.scenario} (episode of {max_steps} steps), seed {args.seed}; policy: a "
            f"randomly initialised MLP actor, sampling; G = {args.group_size} branches of "
            f"H = {args.horizon} steps per decision point; backend {args.backend}"
        )

        # 1. Branch, keep the best, continue from its final state, until the episode ends.
        res = multi_turn_rollout(env, actor, roots, args.group_size, args.horizon, select="best")
        trunk = res.trunk(0)
        trunk_rewards = trunk["next", "reward"].reshape(-1).double().numpy()
        print(f"\n{res.groups.shape[0]} decision points:")
        print(f"{'turn':>4} {'step':>5}  {'branch returns':<{7 * args.group_size}} chosen")
        for n in range(res.groups.shape[0]):
            rets = res.groups["branch_return"][n, :, 0, 0].tolist()
            row = "".join(f"{r:7.2f}" for r in rets)
            step = int(res.groups["root_step"][n, 0, 0])
            print(f"{n:>4} {step:>5}  {row} {int(res.selected[n]):>6}")

        # 2. The stitched episode is a real one: replay its actions open-loop.
        replayed = replay(plain, roots["state"][0], trunk["action"])
        exact = torch.equal(replayed.reshape(-1), trunk["next", "reward"].reshape(-1))
        print(
            f"replaying the trunk's {trunk.shape[0]} actions from the start reproduces its "
            f"rewards bit for bit: {exact}"
        )

        # 3. The same policy from the same start, without branching.
        baseline = branch_rollout(env, actor, roots, group_size=args.group_size, horizon=max_steps)
    finally:
        shutdown_env(env)

    mt_return = float(trunk_rewards.sum())
    mt_crashed = bool(trunk["next", "crashed"].any())
    base_returns = baseline["branch_return"][0, :, 0, 0].double()
    base_crash = (baseline["next", "crashed"][0].squeeze(-1) & baseline["mask"][0]).any(-1)
    print(
        f"\nmulti-turn (best of {args.group_size} every {args.horizon} steps): episode return "
        f"{mt_return:.2f} over {trunk.shape[0]} steps, crashed: {mt_crashed}, "
        f"episode ended: {bool(res.ended[0])}"
    )
    print(
        f"no branching ({args.group_size} rollouts of the same policy from the same start): "
        f"return {base_returns.mean():.2f} ± {base_returns.std():.2f} "
        f"(min {base_returns.min():.2f}, max {base_returns.max():.2f}), "
        f"crash rate {100 * base_crash.double().mean():.0f}%"
    )
    gain = mt_return - float(base_returns.mean())
    print(f"gain of select-and-continue over the no-branching mean: {gain:+.2f}")

    # 4. Pictures.
    # The trunk's row 0 holds the root's position, each row's "next" the one after it.
    trunk_xy = np.concatenate(
        [
            trunk["ego_position"][:1].double().numpy(),
            trunk["next", "ego_position"].double().numpy(),
        ]
    )
    paths = {
        "trunk and branches": args.out / "trunk_and_branches.png",
        "branch returns": args.out / "branch_returns.png",
        "episode return": args.out / "episode_return.png",
    }
    lanes = int(env_config.get("lanes_count", 3))
    plot_trunk(res, trunk_xy, lanes, paths["trunk and branches"])
    plot_branch_returns(res, paths["branch returns"])
    decision_steps = res.groups["root_step"][:, 0, 0].numpy()
    plot_episode_return(trunk_rewards, baseline, decision_steps, paths["episode return"])
    print("\npictures:")
    for label, path in paths.items():
        print(f"  {label:<19} {path}")
    print(f"done in {time.perf_counter() - t_start:.1f} s")


if __name__ == "__main__":
    main()
