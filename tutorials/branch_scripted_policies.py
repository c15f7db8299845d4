# ruff: noqa: T201
"""Branch five scripted drivers from one exact snapshot, and rank them.

This is the original prototype's demo on highway-env. It teaches:

* driving an episode to a *decision point* and taking a snapshot of the whole simulator
  with ``env.get_state()`` (a TensorDict of tensors);
* restoring that snapshot with ``env.reset(TensorDict(state=...), set_state=True)`` and
  checking, with :func:`torchrl_grpo.envs.states_equal`, that every branch starts from
  bitwise the same world;
* running five of the library's scripted policies from it (aggressive, conservative,
  left lane change, right lane change, cautious), ranking them by return, and reading
  what the env reports per step (reward, ``ego_position``, ``speed``, ``crashed``);
* doing the same in one call with :func:`torchrl_grpo.branching.branch_rollout` (a
  group of five branches whose policy depends on the branch index) and drawing it with
  :func:`torchrl_grpo.branching.plot_group`.

Run it::

    python tutorials/branch_scripted_policies.py           # about 15 s on 2 cores
    python tutorials/branch_scripted_policies.py --quick   # the short form the tests run

Pictures (in ``--out``, default ``outputs/tutorials/branch_scripted_policies``):
``rewards_over_time.png``, ``trajectories.png``, ``reward_distribution.png``,
``distance_vs_return.png`` and ``group.png``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display needed

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict, TensorDictBase  # noqa: E402

from torchrl_grpo.branching import branch_rollout, make_roots, plot_group  # noqa: E402
from torchrl_grpo.envs import HighwayEnv, states_equal  # noqa: E402
from torchrl_grpo.modules import KinematicsLayout, RulePolicy, ScriptedPolicy  # noqa: E402
from torchrl_grpo.modules.scripted.policies import (  # noqa: E402
    AggressivePolicy,
    CautiousPolicy,
    ConservativePolicy,
    LaneChangePolicy,
)

NAME = "branch_scripted_policies"


@dataclass
class Branch:
    """One scripted policy's rollout from the snapshot."""

    name: str
    data: TensorDictBase  # [T] steps, as env.rollout returns them
    start_position: np.ndarray  # ego (x, y) at the snapshot
    same_start: bool  # the restored world equals the snapshot, bit for bit

    @property
    def rewards(self) -> np.ndarray:
        """Per-step rewards."""
        return self.data["next", "reward"].reshape(-1).double().numpy()

    @property
    def ret(self) -> float:
        """The branch's return (sum of its rewards)."""
        return float(self.rewards.sum())

    @property
    def positions(self) -> np.ndarray:
        """Ego (x, y) from the snapshot to the branch's end, ``[T + 1, 2]``."""
        after = self.data["next", "ego_position"].double().numpy()
        return np.concatenate([self.start_position[None], after])

    @property
    def crashed(self) -> bool:
        """Whether the ego crashed."""
        return bool(self.data["next", "crashed"].any())

    @property
    def distance(self) -> float:
        """Metres travelled along the road (x)."""
        return float(self.positions[-1, 0] - self.positions[0, 0])

    @property
    def mean_speed(self) -> float:
        """Mean speed over the branch (m/s)."""
        return float(self.data["next", "speed"].double().mean())


def make_policies(layout: KinematicsLayout) -> dict[str, ScriptedPolicy]:
    """The five branch policies of the prototype, reading the scene through ``layout``."""
    return {
        "aggressive": AggressivePolicy(layout),
        "conservative": ConservativePolicy(layout),
        "left": LaneChangePolicy("left", layout),
        "right": LaneChangePolicy("right", layout),
        "cautious": CautiousPolicy(layout),
    }


class PerBranchPolicy:
    """Branch ``g`` of a group plays ``policies[g]``: several drivers in one group.

    :func:`~torchrl_grpo.branching.branch_rollout` hands the policy a tensordict
    holding the observations and each row's ``"branch"`` index; scripted policies are
    stateless, so each one is asked for every row and the right answer is kept.
    """

    def __init__(self, policies: list[ScriptedPolicy]) -> None:
        self.policies = policies

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        """Write ``"action"``: the action of the policy of each row's branch."""
        actions = torch.stack([p(td.clone())["action"] for p in self.policies])  # [P, W]
        td["action"] = actions.gather(0, td["branch"].unsqueeze(0)).squeeze(0)
        return td


def drive_to_decision_point(env: HighwayEnv, layout: KinematicsLayout, seed: int, steps: int):
    """Drive episode ``seed`` ``steps`` steps with the rule-based driver; return the path."""
    env.set_seed(seed)  # seeds the next reset
    td = env.reset()
    trunk = env.rollout(steps, RulePolicy(layout), auto_reset=False, tensordict=td)
    if trunk["next", "done"].any():
        raise SystemExit(
            f"the episode ended after {trunk.shape[0]} steps, before the decision point; "
            "pick another --seed or a smaller --warmup"
        )
    start = td["ego_position"].double().numpy()[None]
    return np.concatenate([start, trunk["next", "ego_position"].double().numpy()])


def run_branch(
    env: HighwayEnv, snapshot: TensorDict, name: str, policy: ScriptedPolicy, horizon: int
) -> Branch:
    """Restore the snapshot, check it bit for bit, roll ``policy`` out for ``horizon`` steps."""
    td0 = env.reset(TensorDict(state=snapshot.clone()), set_state=True)
    # get_state() encodes the live simulator again: equal bits = the same world.
    same = states_equal(env.get_state(), snapshot)
    data = env.rollout(
        horizon, policy, auto_reset=False, tensordict=td0.exclude("state"), break_when_any_done=True
    )
    return Branch(name, data, td0["ego_position"].double().numpy(), same)


def same_steps(group_branch: TensorDictBase, branch: Branch) -> bool:
    """Whether a branch of a ``[T]`` group slice took bitwise the same steps as ``branch``."""
    steps = group_branch[group_branch["mask"]]  # the steps the branch took
    keys = ["action", ("next", "reward"), ("next", "ego_position"), ("next", "crashed")]
    return all(torch.equal(steps[k], branch.data[k]) for k in keys)


# ---------------------------------------------------------------------------- plots
def plot_rewards(branches: list[Branch], colors: dict, path: Path) -> None:
    """Per-step reward and running return of every branch against the step."""
    fig, (ax_r, ax_c) = plt.subplots(1, 2, figsize=(11, 4))
    for i, b in enumerate(branches):
        t = np.arange(1, len(b.rewards) + 1)
        lw = 4.0 - 0.6 * i  # drawn widest first: identical branches stay visible
        ax_r.plot(t, b.rewards, "-o", ms=3, lw=lw, color=colors[b.name], label=b.name)
        ax_c.plot(t, np.cumsum(b.rewards), lw=lw, color=colors[b.name], label=b.name)
        if b.crashed:
            ax_c.plot(t[-1], b.ret, "x", color=colors[b.name], ms=10, mew=2)
    ax_r.set(xlabel="step after the snapshot", ylabel="reward", title="reward per step")
    ax_c.set(xlabel="step after the snapshot", ylabel="return so far", title="running return")
    ax_c.legend(fontsize=8, title="x: crash", title_fontsize=8)
    for ax in (ax_r, ax_c):
        ax.grid(alpha=0.3)
    fig.suptitle("rewards per branch over time")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_trajectories(
    branches: list[Branch], trunk: np.ndarray, colors: dict, lanes: int, path: Path
) -> None:
    """Ego x-y paths: the drive to the decision point, then every branch from it."""
    fig, ax = plt.subplots(figsize=(11, 3.8))
    for y in np.arange(lanes + 1) * 4.0 - 2.0:  # lane boundaries (4 m lanes, centres 0, 4, ..)
        ax.axhline(y, color="0.85", lw=1, ls="-" if y in (-2.0, lanes * 4.0 - 2.0) else "--")
    ax.plot(trunk[:, 0], trunk[:, 1], color="0.4", lw=2, label="drive to the decision point")
    for i, b in enumerate(branches):
        xy = b.positions
        lw = 4.0 - 0.6 * i  # drawn widest first: identical paths stay visible
        ax.plot(xy[:, 0], xy[:, 1], color=colors[b.name], lw=lw, label=f"{b.name} ({b.ret:.2f})")
        ax.plot(*xy[-1], "x" if b.crashed else "o", color=colors[b.name], ms=9 if b.crashed else 4)
    ax.plot(*trunk[-1], "k*", ms=14, label="snapshot")
    ax.invert_yaxis()  # highway-env's y points to the right-hand side of the road
    ax.set(xlabel="x (m)", ylabel="y (m)", title="ego trajectories from the same snapshot")
    ax.legend(fontsize=8, ncol=2, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_reward_distribution(branches: list[Branch], colors: dict, path: Path) -> None:
    """Box plot of every policy's per-step rewards, with the rewards themselves."""
    fig, ax = plt.subplots(figsize=(8, 4))
    data = [b.rewards for b in branches]
    box = ax.boxplot(data, patch_artist=True, widths=0.5, showfliers=False)
    ax.set_xticks(range(1, len(branches) + 1), [b.name for b in branches])
    rng = np.random.default_rng(0)  # jitter only
    for i, b in enumerate(branches, start=1):
        box["boxes"][i - 1].set(facecolor=colors[b.name], alpha=0.35)
        jitter = rng.uniform(-0.12, 0.12, len(b.rewards))
        ax.plot(i + jitter, b.rewards, ".", color=colors[b.name], ms=5)
    ax.set(ylabel="reward per step", title="reward distribution per policy")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_distance_vs_return(branches: list[Branch], colors: dict, path: Path) -> None:
    """Each branch as a point: metres travelled against return (a cross if it crashed)."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    points: dict[tuple[float, float], list[str]] = {}  # branches that ended alike share a label
    for b in branches:
        ax.plot(b.distance, b.ret, "X" if b.crashed else "o", color=colors[b.name], ms=11)
        points.setdefault((round(b.distance, 1), round(b.ret, 2)), []).append(b.name)
    for (x, y), names in points.items():
        ax.annotate(" = ".join(names), (x, y), xytext=(7, 4), textcoords="offset points")
    ax.set(xlabel="distance travelled (m)", ylabel="return", title="distance vs return")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="highway-fast-v0", help="highway-env scenario")
    p.add_argument("--seed", type=int, default=6, help="episode seed")
    p.add_argument("--warmup", type=int, default=None, help="steps to the decision point")
    p.add_argument("--horizon", type=int, default=None, help="steps per branch")
    p.add_argument("--quick", action="store_true", help="short form (tests): fewer steps")
    p.add_argument("--out", type=Path, default=Path("outputs/tutorials") / NAME)
    args = p.parse_args(argv)
    args.warmup = args.warmup or (5 if args.quick else 10)
    args.horizon = args.horizon or (8 if args.quick else 20)
    return args


def main(argv: list[str] | None = None) -> None:
    """Snapshot, branch five drivers, rank them, draw the pictures."""
    args = parse_args(argv)
    t_start = time.perf_counter()
    torch.manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)

    # 1. Drive to the decision point and snapshot the whole simulator.
    env = HighwayEnv(args.scenario)
    layout = KinematicsLayout.from_highway_config(env.config)
    trunk = drive_to_decision_point(env, layout, args.seed, args.warmup)
    snapshot = env.get_state()
    n_vehicles = int(snapshot["sim", "entities", "i16"].shape[0])
    print(
        f"decision point: {args.scenario}, seed {args.seed}, after {args.warmup} steps of the "
        f"rule-based driver; ego at x = {trunk[-1, 0]:.1f} m, y = {trunk[-1, 1]:.1f} m; "
        f"snapshot holds {n_vehicles} vehicle slots"
    )

    # 2. Five branches from that exact snapshot, verified bit for bit.
    policies = make_policies(layout)
    branches = [run_branch(env, snapshot, n, p, args.horizon) for n, p in policies.items()]
    all_same = all(b.same_start for b in branches)
    print(f"all {len(branches)} branches started from bitwise the same state: {all_same}")

    # 3. Rank them by return.
    ranked = sorted(branches, key=lambda b: b.ret, reverse=True)
    print(f"\nranking over {args.horizon} steps from the snapshot:")
    header = (
        f"{'rank':>4}  {'policy':<13}{'return':>8}{'steps':>7}{'crashed':>9}"
        f"{'distance (m)':>14}{'speed (m/s)':>13}{'same start':>12}"
    )
    print(header)
    print("-" * len(header))
    for rank, b in enumerate(ranked, start=1):
        print(
            f"{rank:>4}  {b.name:<13}{b.ret:>8.2f}{len(b.rewards):>7}{str(b.crashed):>9}"
            f"{b.distance:>14.1f}{b.mean_speed:>13.1f}{str(b.same_start):>12}"
        )
    best = ranked[0]
    print(f"best: {best.name} (return {best.ret:.2f})")
    if best.crashed:
        print(
            f"note: the best branch crashed, at step {len(best.rewards)} of {args.horizon}: "
            "over a fixed horizon a late crash only costs the steps it cuts off. Training "
            "prices in what a crash forfeits with the horizon bootstrap (docs/training.md)."
        )

    # 4. The same group in one call: branch g plays policy g. Same world, same bits.
    group = branch_rollout(
        env,
        PerBranchPolicy(list(policies.values())),
        make_roots(snapshot, root_step=args.warmup),
        group_size=len(policies),
        horizon=args.horizon,
    )
    identical = all(same_steps(group[0, g], b) for g, b in enumerate(branches))
    print(
        f"branch_rollout (one group of {len(policies)}, branch g plays policy g) "
        f"reproduces the five branches bit for bit: {identical}"
    )

    # 5. Pictures.
    colors = {n: plt.get_cmap("tab10")(i) for i, n in enumerate(policies)}
    lanes = int(env.config.get("lanes_count", 3))
    paths = {
        "rewards over time": args.out / "rewards_over_time.png",
        "trajectories": args.out / "trajectories.png",
        "reward distribution": args.out / "reward_distribution.png",
        "distance vs return": args.out / "distance_vs_return.png",
        "branch group (plot_group)": args.out / "group.png",
    }
    plot_rewards(branches, colors, paths["rewards over time"])
    plot_trajectories(branches, trunk, colors, lanes, paths["trajectories"])
    plot_reward_distribution(branches, colors, paths["reward distribution"])
    plot_distance_vs_return(branches, colors, paths["distance vs return"])
    title = f"{len(policies)} scripted drivers: " + ", ".join(
        f"{g}={n}" for g, n in enumerate(policies)
    )
    plot_group(group, 0, path=paths["branch group (plot_group)"], title=title)
    env.close()
    print("\npictures:")
    for label, path in paths.items():
        print(f"  {label:<27} {path}")
    print(f"done in {time.perf_counter() - t_start:.1f} s")


if __name__ == "__main__":
    main()
