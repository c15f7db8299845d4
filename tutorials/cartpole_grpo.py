# ruff: noqa: T201
"""Tutorial: extend the library with a new env, CartPole-v1, and train it with GRPO to 500.

Run ``python tutorials/cartpole_grpo.py [--quick] [--out DIR] [--seed N]``.

What it shows, in order:

1. **A new simulator through the state-codec interface.** ``torchrl_grpo`` can branch
   from any gymnasium env whose complete state a :class:`~torchrl_grpo.envs.StateCodec`
   turns into a TensorDict of tensors and back. ``SnapshotEnv("CartPole-v1",
   codec=CartPoleStateCodec())`` wraps gymnasium's CartPole for TorchRL with such a
   codec; the codec is ``torchrl_grpo/envs/cartpole.py``, 90 lines. Writing one
   for your own simulator means subclassing ``StateCodec``: three methods, two optional::

       class MyCodec(StateCodec):
           def state_spec(self):          # fixed keys, shapes, dtypes of a state
               return Composite(physics=Unbounded((4,), dtype=torch.int64),  # f64 as bits
                                rng=rng_spec(), wrappers=wrapper_spec())
           def encode(self, env):         # the gymnasium env -> a new TensorDict
               ...                        # (floats stored as integer bit patterns)
           def decode(self, env, state):  # check *everything* first, then write into env
               ...                        # (raise a SnapshotError, env left untouched)
           def reseed(self, state, seed): # optional: a copy with a fresh RNG stream
               return with_seeded_rng(state, "rng", seed)
           def fingerprint(self, env):    # optional: which config a state belongs to
               ...

   (``bind`` and ``validate`` are optional hooks too; ``torchrl_grpo.envs.core.gym_state``
   holds helpers for numpy generators and the TimeLimit / OrderEnforcing wrappers.)
   Then ``SnapshotEnv(env_id, codec=MyCodec())``, or ``register_codec(env_id, MyCodec)``
   once and ``SnapshotEnv(env_id)``. Section 1 checks the specs and runs a bitwise
   snapshot / restore round trip.
2. **A hand-written rule policy**: push the cart towards where the pole is falling,
   ``action = 1 if theta + K * theta_dot > 0 else 0`` (a PD controller on the angle).
3. **GRPO**: groups of G rollouts of a small MLP policy that all start from the same
   snapshot (an episode start, ``reset_roots`` + ``branch_rollout``), each scored
   against the other members of its group (``GroupRelativeAdvantage``, here per step:
   a step's reward-to-go against the group's at the same step), optimised with the
   clipped ``GRPOLoss`` and Adam. The
   greedy policy is evaluated periodically; training stops when it reaches the maximum
   return of 500 (CartPole-v1 truncates at 500 steps) on every evaluation episode.
4. **The comparison** (rule vs GRPO on 10 held-out episodes) and two pictures: the
   learning curve, and one group's branches from their shared snapshot.

``--quick`` runs the same code with a tiny budget (seconds), for the test.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type
from torchrl.modules import MLP

# Section 4's pictures, and the constants they share (tutorials/tutorial_figures/cartpole.py).
from tutorial_figures.cartpole import (
    ENV_ID,
    MAX_RETURN,
    plot_curve,
    plot_group,
)

from torchrl_grpo.branching import branch_rollout, reset_roots, shutdown_env
from torchrl_grpo.envs import (
    CartPoleStateCodec,
    SnapshotEnv,
    SnapshotSerialEnv,
    from_bits,
    state_differences,
)
from torchrl_grpo.modules import make_discrete_actor
from torchrl_grpo.objectives import GroupRelativeAdvantage, GRPOLoss


@dataclass
class Budget:
    """Everything ``--quick`` shrinks; the algorithm is the same."""

    max_frames: int  # training env steps (branch steps) before giving up
    eval_episodes: int  # greedy episodes per periodic evaluation
    final_episodes: int  # held-out episodes of the final comparison (a multiple of eval)


FULL = Budget(max_frames=250_000, eval_episodes=10, final_episodes=10)
QUICK = Budget(max_frames=1_500, eval_episodes=10, final_episodes=10)

# GRPO hyper-parameters (found on 1 CPU core; see tutorials/cartpole_grpo.md).
GROUP_SIZE = 8  # G branches per snapshot
ROOTS_PER_BATCH = 4  # R snapshots (episode starts) per batch: R x G rollouts
HORIZON = MAX_RETURN  # a branch runs to the end of its episode
GAMMA = 0.99  # discount of the per-step returns (see train())
EPOCHS = 10  # passes over each batch (the clip keeps the updates near the behaviour policy)
MINIBATCH = 512  # steps per gradient step
LR = 1e-3
CLIP = 0.2
RULE_GAIN = 0.5  # K in theta + K * theta_dot


# ---------------------------------------------------------------------------- 1. the env
def make_env(seed: int | None = None) -> SnapshotEnv:
    """CartPole-v1 as a TorchRL env whose complete state is a TensorDict.

    ``codec=`` is spelt out to show where a codec plugs in; without it, SnapshotEnv
    looks up the codec registered for the env id (``register_codec``), here the same.
    """
    return SnapshotEnv(ENV_ID, codec=CartPoleStateCodec(), seed=seed)


def snapshot_round_trip(seed: int) -> None:
    """Snapshot mid-episode, let the world move on, restore, replay: compare bit for bit."""
    env = make_env(seed)
    check_env_specs(env)
    print(f"check_env_specs({ENV_ID}): ok; codec: {type(env.codec).__name__}")
    env.reset()
    push = [TensorDict(action=torch.tensor(a)) for a in (1, 0, 1, 1, 0)]
    for action in push:  # a few steps into the episode
        env.step(action.clone())
    state = env.get_state()
    physics = from_bits(state["sim", "physics"], torch.float64)  # floats are stored as bits
    print(
        f"snapshot: {len(list(state.keys(True, True)))} tensors "
        f"{sorted(k if isinstance(k, str) else '/'.join(k) for k in state.keys(True, True))}"
    )
    print(f"  physics (x, x_dot, theta, theta_dot) = {[round(v, 4) for v in physics.tolist()]}")

    generator = torch.Generator().manual_seed(seed)
    actions = torch.randint(0, 2, (40,), generator=generator)

    def replay() -> tuple[list[TensorDictBase], TensorDictBase]:
        outs = [env.step(TensorDict(action=a.clone()))["next"] for a in actions]
        return outs, env.get_state()

    with warnings.catch_warnings():
        # 40 random pushes usually drop the pole: gymnasium then warns on every step, but
        # keeps stepping (the codec stores its steps_beyond_terminated counter too).
        warnings.filterwarnings("ignore", message=".*already returned terminated")
        first, end_first = replay()  # the world moves on
        env.reset(TensorDict(state=state), set_state=True)  # back to the snapshot
        second, end_second = replay()
    same_steps = all(not state_differences(a, b) for a, b in zip(first, second, strict=True))
    diffs = state_differences(end_first, end_second)
    print(
        f"restore + the same {len(actions)} actions: step outputs identical: {same_steps}, "
        f"final simulator state bitwise identical: {not diffs}"
    )
    if not same_steps or diffs:
        raise SystemExit(f"the restore was not exact: {diffs}")
    env.close()


# ---------------------------------------------------------------------------- evaluation
def episode_returns(data: TensorDictBase) -> torch.Tensor:
    """Per env of a batched rollout ``[N, T]``: the return up to its first ``done``."""
    done = data["next", "done"].squeeze(-1).long()
    alive = (done.cumsum(-1) - done) == 0  # steps up to and including the first done
    return (data["next", "reward"].squeeze(-1) * alive).sum(-1)


def evaluate(eval_env: SnapshotSerialEnv, policy, episodes: int, seed: int) -> torch.Tensor:
    """Returns of ``episodes`` greedy episodes (N at a time on the N workers)."""
    returns = []
    for chunk in range(math.ceil(episodes / eval_env.batch_size[0])):
        eval_env.set_seed(seed + 1000 * chunk)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            data = eval_env.rollout(
                MAX_RETURN, policy, break_when_any_done=False, break_when_all_done=True
            )
        returns.append(episode_returns(data))
    return torch.cat(returns)[:episodes]


# ---------------------------------------------------------------------------- 2. the rule
class RulePolicy:
    """Push towards where the pole is falling: ``1`` (right) if theta + K theta_dot > 0.

    The observation is (x, x_dot, theta, theta_dot); theta > 0 leans right.
    """

    def __init__(self, gain: float = RULE_GAIN) -> None:
        self.gain = gain

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        """Write the rule's ``"action"`` into ``td`` (any batch shape)."""
        obs = td["observation"]
        td["action"] = (obs[..., 2] + self.gain * obs[..., 3] > 0).long()
        return td


# ---------------------------------------------------------------------------- 3. GRPO
def make_actor(env: SnapshotEnv) -> nn.Module:
    """A 4 -> 64 -> 64 -> 2 MLP of logits, as a categorical TorchRL actor."""
    net = MLP(in_features=4, out_features=2, num_cells=[64, 64], activation_class=nn.Tanh)
    return make_discrete_actor(net, env.action_spec)


@dataclass
class GroupRecord:
    """One group kept for the branch picture."""

    observation: torch.Tensor  # [G, T, 4]
    mask: torch.Tensor  # [G, T]
    returns: torch.Tensor  # [G]
    terminated: torch.Tensor  # [G]: the pole fell or the cart left the track
    iteration: int


def train(args, budget: Budget, root_env, branch_env, eval_env, actor, log) -> dict:
    """The GRPO loop: branch groups, group-relative advantages, clipped loss, Adam."""
    # CartPole pays 1 per step, so a branch's return is just its length, and outcome
    # supervision (returns="branch": one advantage for all the steps of a branch) credits
    # 500 steps for a failure that happened near the end. returns="step" (DeepSeekMath's
    # process supervision) compares each step's discounted reward-to-go with the other
    # branches of its group *at the same step from the shared snapshot*: branches that are
    # about to fail score low exactly where they go wrong. (With returns="branch" some
    # seeds stalled below 500; see tutorials/cartpole_grpo.md.)
    advantage = GroupRelativeAdvantage(returns="step", gamma=GAMMA)
    loss_fn = GRPOLoss(actor, clip_epsilon=CLIP, entropy_bonus=False, aggregation="dapo")
    optim = torch.optim.Adam(loss_fn.parameters(), lr=LR)

    frames, iteration, next_group = 0, 0, 0
    start = time.perf_counter()
    curve = [(0, evaluate(eval_env, actor, budget.eval_episodes, args.eval_seed))]
    best_group: GroupRecord | None = None
    reached = None
    log(f"iter {0:3d}  frames {0:6d}  greedy eval {curve[-1][1].mean():5.1f}")
    while frames < budget.max_frames:
        iteration += 1
        t0 = time.perf_counter()
        # R episode starts (seeded): each one is the shared snapshot of a group.
        # (trunk_roots(root_env, actor, every=K) would give decision points along
        # trunks of the current policy instead: vine-style groups from mid-episode.)
        roots = reset_roots(root_env, ROOTS_PER_BATCH, seed=args.seed * 100_003 + iteration)
        # G rollouts of the current (sampling) policy from every root: [R, G, T].
        data = branch_rollout(
            branch_env, actor, roots, GROUP_SIZE, HORIZON, first_group_id=next_group
        )
        next_group += ROOTS_PER_BATCH
        frames += int(data["mask"].sum())
        data = advantage(data)  # writes data["advantage"], [R, G, T, 1]
        best_group = keep_most_diverse(best_group, data, iteration)
        t1 = time.perf_counter()

        steps = data[data["mask"]]  # the valid steps, flattened: [N]
        for _ in range(EPOCHS):
            for idx in torch.randperm(steps.shape[0]).split(MINIBATCH):
                losses = loss_fn(steps[idx])  # the clipped ratio objective, mean over steps
                optim.zero_grad()
                losses["loss_objective"].backward()
                nn.utils.clip_grad_norm_(loss_fn.parameters(), 1.0)
                optim.step()
        t2 = time.perf_counter()

        evals = evaluate(eval_env, actor, budget.eval_episodes, args.eval_seed)
        curve.append((frames, evals))
        returns = data["branch_return"][..., 0, 0]  # [R, G]
        log(
            f"iter {iteration:3d}  frames {frames:6d}  sampled return {returns.mean():5.1f}  "
            f"greedy eval {evals.mean():5.1f} (min {evals.min():3.0f})  "
            f"[rollout {t1 - t0:4.1f} s, update {t2 - t1:4.1f} s, "
            f"eval {time.perf_counter() - t2:4.1f} s]  total {time.perf_counter() - start:5.1f} s"
        )
        if bool((evals >= MAX_RETURN).all()):
            reached = {"frames": frames, "seconds": time.perf_counter() - start}
            log(f"greedy policy at {MAX_RETURN} on all {len(evals)} evaluation episodes")
            break
    return {
        "frames": frames,
        "seconds": time.perf_counter() - start,
        "iterations": iteration,
        "curve": curve,
        "group": best_group,
        "reached": reached,
    }


def keep_most_diverse(best: GroupRecord | None, data: TensorDictBase, it: int) -> GroupRecord:
    """Keep the group whose branch returns differ the most (the clearest picture)."""
    returns = data["branch_return"][..., 0, 0]  # [R, G]
    spread = returns.std(-1)
    r = int(spread.argmax())
    if best is not None and float(best.returns.std()) >= float(spread[r]):
        return best
    mask = data["mask"][r]
    last = (mask.sum(-1) - 1).clamp(min=0)
    terminated = data["next", "terminated"][r].squeeze(-1)[torch.arange(mask.shape[0]), last]
    return GroupRecord(data["observation"][r], mask, returns[r], terminated, it)


# ---------------------------------------------------------------------------- main
def main() -> None:
    """Run the tutorial: env + codec, rule policy, GRPO training, table and pictures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny budget (for the test)")
    parser.add_argument("--out", type=Path, default=Path("outputs/tutorials/cartpole_grpo"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.eval_seed = 1_000_000 + 1000 * args.seed  # periodic evaluation episodes
    final_seed = 2_000_000 + 1000 * args.seed  # held-out episodes of the final table
    budget = QUICK if args.quick else FULL
    args.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)  # the policy samples from torch's global generator
    torch.set_num_threads(1)
    t_start = time.perf_counter()

    print(f"== 1. {ENV_ID} through the state-codec interface")
    snapshot_round_trip(args.seed)

    # The envs: roots (episode starts) come from one env; the G branches of a group run
    # on G workers of a SerialEnv in this process, so the policy acts on a batch of G
    # (a CartPole step takes microseconds: worker processes spend more on communication
    # than they save. BranchParallelEnv(2, make_env) ran 480 us per branch step, this
    # SerialEnv 150 us.)
    root_env = make_env(args.seed)
    branch_env = SnapshotSerialEnv(GROUP_SIZE, make_env)
    eval_env = SnapshotSerialEnv(budget.eval_episodes, make_env)
    try:
        print("\n== 2. rule policy: push right if theta + K * theta_dot > 0")
        for gain in (0.0, 0.1, RULE_GAIN, 1.0):
            r = evaluate(eval_env, RulePolicy(gain), budget.eval_episodes, args.eval_seed)
            print(f"  K = {gain:<4}: mean return {r.mean():6.1f} (min {r.min():.0f})")
        t0 = time.perf_counter()
        rule_returns = evaluate(eval_env, RulePolicy(), budget.final_episodes, final_seed)
        rule_seconds = time.perf_counter() - t0

        print(f"\n== 3. GRPO: {ROOTS_PER_BATCH} snapshots x {GROUP_SIZE} branches per batch")
        actor = make_actor(root_env)
        result = train(args, budget, root_env, branch_env, eval_env, actor, print)
        grpo_returns = evaluate(eval_env, actor, budget.final_episodes, final_seed)
    finally:
        for env in (branch_env, eval_env):
            shutdown_env(env)
        root_env.close()

    print(f"\n== 4. rule vs GRPO, {budget.final_episodes} held-out greedy episodes")
    header = (
        f"{'policy':<12} {'mean return':>11} {'min':>6} {'max':>6} {'frames':>8} {'time [s]':>9}"
    )
    print(header)
    print("-" * len(header))
    rows = [
        ("rule", rule_returns, 0, rule_seconds),
        ("GRPO", grpo_returns, result["frames"], result["seconds"]),
    ]
    for name, r, frames, seconds in rows:
        print(
            f"{name:<12} {r.mean():11.1f} {r.min():6.0f} {r.max():6.0f} {frames:8d} {seconds:9.1f}"
        )
    print("(frames: training env steps; time: training wall-clock, or the rule's evaluation)")
    reached = result["reached"]
    if reached is not None:
        print(
            f"GRPO reached {MAX_RETURN} on all periodic eval episodes after {reached['frames']} "
            f"frames, {reached['seconds']:.1f} s, {result['iterations']} iterations"
        )
    else:
        print(f"GRPO did not reach {MAX_RETURN} within {budget.max_frames} frames")

    curve_png = args.out / "learning_curve.png"
    group_png = args.out / "group_branches.png"
    plot_curve(curve_png, result["curve"], float(rule_returns.mean()), reached, GROUP_SIZE)
    plot_group(group_png, result["group"])
    summary = {
        "quick": args.quick,
        "seed": args.seed,
        "rule": {"returns": rule_returns.tolist(), "seconds": rule_seconds},
        "grpo": {
            "returns": grpo_returns.tolist(),
            "frames": result["frames"],
            "seconds": result["seconds"],
            "iterations": result["iterations"],
            "reached_max": reached,
        },
        "curve": [(f, r.tolist()) for f, r in result["curve"]],
        "total_seconds": time.perf_counter() - t_start,
    }
    (args.out / "results.json").write_text(json.dumps(summary, indent=1))
    print(f"\nwrote {curve_png}, {group_png}, {args.out / 'results.json'}")
    print(f"total wall-clock {time.perf_counter() - t_start:.1f} s")


if __name__ == "__main__":
    main()
