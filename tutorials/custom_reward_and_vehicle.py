# ruff: noqa: T201
"""A custom reward and a custom vehicle class, both compatible with exact snapshots.

Part 1, a custom reward. Every step of a :class:`~torchrl_grpo.envs.HighwayEnv` carries
highway-env's reward components (``("next", "reward_components", name)``). A TorchRL
``Transform`` re-weights them into a new reward, leaving the simulator, and so its
snapshots, untouched; branch rollouts on the transformed env score branches with the
new reward. The highway-env way, a config change (``collision_reward`` etc. with
``normalize_reward=False``), gives the same rewards, but makes another env: its
snapshots do not restore into the default env (``StateMismatchError``).

Part 2, a custom vehicle class. ``PatientIDM`` is an ``IDMVehicle`` with two extra
attributes, ``patience`` (seconds it accepts behind a slower leader, drawn from the
road's generator) and ``stuck`` (seconds spent behind one so far): it changes lane only
once ``stuck`` exceeds ``patience``. Registered with
:func:`~torchrl_grpo.envs.register_vehicle_class`, it is used as the traffic
(highway-env's ``other_vehicles_type``), the snapshot stores both fields, and a restore
gives them back bit for bit. A class with an attribute that was not registered fails
when the env is built (it fixes its state layout then), with an ``UnknownFieldError`` naming the
attribute, instead of being silently left out of the state.

Run it::

    python tutorials/custom_reward_and_vehicle.py           # about 15 s on 2 cores
    python tutorials/custom_reward_and_vehicle.py --quick   # the short form the tests run

Pictures (in ``--out``, default ``outputs/tutorials/custom_reward_and_vehicle``):
``reward_components.png`` and ``patience.png``.
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
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402
from tensordict import TensorDict, TensorDictBase  # noqa: E402
from torchrl.data import Composite, Unbounded  # noqa: E402
from torchrl.envs import Transform, TransformedEnv  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from torchrl_grpo.branching import branch_rollout, make_roots  # noqa: E402
from torchrl_grpo.envs import (  # noqa: E402
    Field,
    HighwayEnv,
    StateMismatchError,
    UnknownFieldError,
    register_vehicle_class,
    states_equal,
)
from torchrl_grpo.modules import ConstantActionPolicy, KinematicsLayout, RandomPolicy  # noqa: E402
from torchrl_grpo.modules.scripted.policies import AggressivePolicy  # noqa: E402

NAME = "custom_reward_and_vehicle"

#: "Safety first": a crash costs 5 (highway-env's default weight is -1), speed and the
#: right lane earn less than by default, and nothing is normalised.
SAFETY_FIRST = {"collision_reward": -5.0, "high_speed_reward": 0.2, "right_lane_reward": 0.1}


# ---------------------------------------------------------------------------- part 1
class WeightedRewardComponents(Transform):
    """Replace the env's reward by a weighted sum of highway-env's reward components.

    ``reward = on_road * sum_k weights[k] * component_k`` (highway-env's own formula
    with ``normalize_reward=False``). The env's original reward is kept beside it as
    ``"env_reward"`` (an observation entry), so both can be compared on one rollout.

    Args:
        weights: ``{component name: weight}``; names as in ``("reward_components", name)``.
    """

    def __init__(self, weights: dict[str, float]) -> None:
        super().__init__(in_keys=[], out_keys=["reward", "env_reward"])
        self.weights = dict(weights)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        components = next_tensordict.get("reward_components")
        reward = sum(w * components.get(name) for name, w in self.weights.items())
        next_tensordict.set("env_reward", next_tensordict.get("reward"))
        next_tensordict.set("reward", reward * components.get("on_road_reward"))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        tensordict_reset.set("env_reward", torch.zeros(1, device=tensordict_reset.device))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        """Declare ``"env_reward"``: collectors and batched envs follow the specs."""
        observation_spec["env_reward"] = Unbounded(
            (1,), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec


def custom_reward_demo(args: argparse.Namespace) -> tuple[TensorDictBase, dict]:
    """Roll out the aggressive driver under the custom reward; compare both ways."""
    env = TransformedEnv(HighwayEnv(args.scenario), WeightedRewardComponents(SAFETY_FIRST))
    check_env_specs(env)  # the transformed specs match what the env returns
    env.set_seed(args.seed)  # seeds the next reset (rollout() starts with one)
    layout = KinematicsLayout.from_highway_config(env.base_env.config)
    rollout = env.rollout(args.steps, AggressivePolicy(layout), break_when_any_done=True)
    custom = rollout["next", "reward"].reshape(-1)
    default = rollout["next", "env_reward"].reshape(-1)
    crashed = bool(rollout["next", "crashed"].any())
    names = list(rollout["next", "reward_components"].keys())
    print(f"reward components in the env output: {names}")
    print(
        f"aggressive driver, {rollout.shape[0]} steps (crashed: {crashed}): "
        f"return {default.sum():.2f} under highway-env's reward, "
        f"{custom.sum():.2f} under the safety-first reward {SAFETY_FIRST}"
    )

    # The same reward through highway-env's config, on the same actions.
    config = {**SAFETY_FIRST, "normalize_reward": False}
    configured = HighwayEnv(args.scenario, config=config)
    configured.set_seed(args.seed)  # the same episode as the rollout's
    configured.reset()
    replayed = torch.stack(
        [configured.step(TensorDict(action=a.clone()))["next", "reward"] for a in rollout["action"]]
    ).reshape(-1)
    gap = float((replayed - custom).abs().max())
    print(
        f"config {config}: same rewards on the same actions, max |difference| = {gap:.1e} "
        "(highway-env sums in float64, the transform in float32)"
    )
    state = env.base_env.get_state()
    try:
        configured.reset(TensorDict(state=state), set_state=True)
        mismatch = "restored (unexpected)"
    except StateMismatchError as err:
        mismatch = f"StateMismatchError: {err}"
    print(f"a snapshot of the default env restored into the re-configured one -> {mismatch}")

    # Branch rollouts score branches with the transformed reward.
    env.set_seed(args.seed)
    env.reset()
    root = make_roots(env.base_env.get_state())
    group = branch_rollout(env, RandomPolicy(5, seed=args.seed), root, 4, args.branch_horizon)
    mask = group["mask"][0]
    env_returns = (group["next", "env_reward"][0].squeeze(-1) * mask).sum(-1)
    print(
        f"branch_rollout on the transformed env (4 random branches, {args.branch_horizon} "
        f"steps): branch_return {fmt(group['branch_return'][0, :, 0, 0])} (safety first) vs "
        f"{fmt(env_returns)} (highway-env)"
    )
    configured.close()
    env.close()
    return rollout, {"custom": custom, "default": default}


def fmt(values: torch.Tensor) -> str:
    """A short list of numbers."""
    return "[" + ", ".join(f"{float(v):.2f}" for v in values) + "]"


def plot_reward_components(rollout: TensorDictBase, rewards: dict, path: Path) -> None:
    """The reward components over the episode, and the reward built from them both ways."""
    comps = rollout["next", "reward_components"]
    t = np.arange(1, rollout.shape[0] + 1)
    fig, (ax_c, ax_r, ax_b) = plt.subplots(1, 3, figsize=(15, 4.2))
    for name in comps.keys():
        ax_c.plot(t, comps[name].reshape(-1).numpy(), "-o", ms=3, label=name)
    ax_c.set(xlabel="step", ylabel="component value", title="reward components (env output)")
    ax_c.legend(fontsize=8)
    default = rewards["default"].numpy()
    custom = rewards["custom"].numpy()
    ax_r.plot(t, default, "-o", ms=3, label=f"highway-env (return {default.sum():.2f})")
    ax_r.plot(t, custom, "-s", ms=3, label=f"safety first (return {custom.sum():.2f})")
    ax_r.axhline(0, color="0.6", lw=0.8)
    ax_r.set(xlabel="step", ylabel="reward", title="reward per step under both rewards")
    ax_r.legend(fontsize=8)
    # What each component contributes to the return, under each weighting.
    default_w = {"collision_reward": -1.0, "high_speed_reward": 0.4, "right_lane_reward": 0.1}
    names = list(SAFETY_FIRST)
    on_road = comps["on_road_reward"].reshape(-1)
    sums = {n: float((comps[n].reshape(-1) * on_road).sum()) for n in names}
    x = np.arange(len(names))
    span = (
        default_w["high_speed_reward"]
        + default_w["right_lane_reward"]
        - default_w["collision_reward"]
    )  # highway-env's normalisation divides by it (after shifting by the collision weight)
    ax_b.bar(x - 0.2, [default_w[n] * sums[n] / span for n in names], 0.4, label="highway-env")
    ax_b.bar(x + 0.2, [SAFETY_FIRST[n] * sums[n] for n in names], 0.4, label="safety first")
    ax_b.axhline(0, color="0.3", lw=0.8)
    ax_b.set_xticks(x, [n.replace("_reward", "") for n in names])
    ax_b.set(ylabel="contribution to the return", title="return by component")
    ax_b.legend(fontsize=8)
    for ax in (ax_c, ax_r, ax_b):
        ax.grid(alpha=0.3)
    fig.suptitle("one episode of the aggressive driver, scored by two rewards")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------- part 2
class PatientIDM(IDMVehicle):
    """An IDM driver that changes lane only after ``patience`` seconds behind a slow leader.

    Two attributes beyond ``IDMVehicle``'s, both part of the simulator's state:
    ``patience`` (s, drawn per vehicle from the road's generator, so episodes stay
    reproducible) and ``stuck`` (s spent behind a slower leader, updated every
    simulation step).
    """

    PATIENCE_RANGE = (1.0, 6.0)  # s
    FOLLOW_DISTANCE = 40.0  # m: a slower leader closer than this holds the driver up

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.patience = 3.0
        self.stuck = 0.0

    def randomize_behavior(self) -> None:
        """Draw the IDM exponent (as IDMVehicle does) and the patience."""
        super().randomize_behavior()
        self.patience = float(self.road.np_random.uniform(*self.PATIENCE_RANGE))

    def step(self, dt: float) -> None:
        """Count the time spent behind a slower leader, then move."""
        front, _ = self.road.neighbour_vehicles(self, self.lane_index)
        held_up = (
            front is not None
            and front.speed < self.target_speed - 1.0
            and self.lane_distance_to(front) < self.FOLLOW_DISTANCE
        )
        self.stuck = self.stuck + dt if held_up else 0.0
        super().step(dt)

    def change_lane_policy(self) -> None:
        """MOBIL, once the driver has run out of patience (or mid lane change)."""
        if self.lane_index == self.target_lane_index and self.stuck < self.patience:
            return
        super().change_lane_policy()


class MoodyIDM(IDMVehicle):
    """An IDMVehicle with an attribute nobody registered: snapshots must refuse it."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.mood = 0.5


# Register before building an env that uses the classes (an env fixes its state layout
# when it is built). PatientIDM declares its fields; MoodyIDM registers the class only.
register_vehicle_class(PatientIDM, {"patience": Field("float"), "stuck": Field("float")})
register_vehicle_class(MoodyIDM)


def class_path(cls: type) -> str:
    """The dotted path highway-env's ``other_vehicles_type`` takes."""
    return f"{cls.__module__}.{cls.__qualname__}"


def traffic_fields(env: HighwayEnv) -> np.ndarray:
    """``[vehicles, 2]`` live ``(patience, stuck)`` of the traffic, as float64."""
    road = env.gym_env.unwrapped.road
    return np.array([(v.patience, v.stuck) for v in road.vehicles if isinstance(v, PatientIDM)])


def custom_vehicle_demo(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    """Traffic of PatientIDM: a snapshot round trip, and the fields over an episode."""
    config = {"other_vehicles_type": class_path(PatientIDM)}
    env = HighwayEnv(args.scenario, config=config, return_state=True)
    layout = env.codec.layout
    env.set_seed(args.seed)
    env.reset()
    n_patient = sum(isinstance(v, PatientIDM) for v in env.gym_env.unwrapped.road.vehicles)
    print(f"traffic: {n_patient} PatientIDM vehicles ({config['other_vehicles_type']})")
    idle = TensorDict(action=torch.tensor(1))  # the ego keeps its lane and speed
    snap_step, later = 3, max(3, args.steps // 3)  # early on, some traffic is held up
    for _ in range(snap_step):
        env.step(idle.clone())
    snapshot = env.get_state()
    live = traffic_fields(env)
    stored = torch.stack(
        [layout.column(snapshot["sim", "entities"], f) for f in ("patience", "stuck")], -1
    )
    patient = (stored[:, 0] > 0).nonzero().squeeze(-1)  # PatientIDM slots (ego, padding: 0)
    held_up = patient[torch.argsort(stored[patient, 1], descending=True, stable=True)[:3]]
    print(
        f"snapshot at step {snap_step}: patience and stuck stored in every PatientIDM slot; "
        f"the 3 most held up (slots {held_up.tolist()}): patience "
        f"{fmt(stored[held_up, 0])} s, stuck {fmt(stored[held_up, 1])} s"
    )
    # Let the world move on, come back, replay: the same future, bit for bit.
    future = [env.step(idle.clone())["next", "state"] for _ in range(later)]
    env.reset(TensorDict(state=snapshot.clone()), set_state=True)
    restored = traffic_fields(env)
    same_fields = live.shape == restored.shape and np.array_equal(
        live.view(np.int64), restored.view(np.int64)
    )
    replay = [env.step(idle.clone())["next", "state"] for _ in range(later)]
    same_future = all(states_equal(a, b) for a, b in zip(future, replay, strict=True))
    print(f"restored patience and stuck equal the snapshot's, bit for bit: {same_fields}")
    print(f"replaying {len(replay)} steps after the restore gives the same states: {same_future}")

    # The fields over a whole episode, read back from the per-step states.
    env.set_seed(args.seed)
    episode = env.rollout(args.steps, ConstantActionPolicy("IDLE"))
    entities = episode["next", "state", "sim", "entities"]
    patience = layout.column(entities, "patience").numpy()  # [T, slots]
    stuck = layout.column(entities, "stuck").numpy()
    env.close()

    # An attribute nobody registered fails loudly, naming itself, when the env is built
    # (it fixes its state layout then), rather than being silently dropped from the state.
    try:
        moody = HighwayEnv(args.scenario, config={"other_vehicles_type": class_path(MoodyIDM)})
        moody.close()
        print("MoodyIDM: no error (unexpected)")
    except UnknownFieldError as err:
        print(f"MoodyIDM (an unregistered 'mood' attribute) -> UnknownFieldError: {err}")
    return patience, stuck


def plot_patience(patience: np.ndarray, stuck: np.ndarray, path: Path, n_show: int = 6) -> None:
    """``stuck`` against ``patience`` for the vehicles held up the longest."""
    fig, ax = plt.subplots(figsize=(9, 4.5))
    traffic = np.flatnonzero(patience[0] > 0)  # PatientIDM slots (ego, padding: 0)
    order = traffic[np.argsort(-stuck[:, traffic].max(0))][:n_show]
    order = [slot for slot in order if stuck[:, slot].max() > 0] or list(order[:1])
    t = np.arange(1, stuck.shape[0] + 1)
    cmap = plt.get_cmap("tab10")
    for i, slot in enumerate(order):
        color = cmap(i)
        ax.plot(t, stuck[:, slot], color=color, lw=1.8, label=f"vehicle slot {slot}")
        ax.axhline(patience[0, slot], color=color, ls="--", lw=1)
    ax.set(
        xlabel="step (1 s)",
        ylabel="seconds",
        title="PatientIDM traffic: time held up (solid) vs patience (dashed), from the states",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="highway-fast-v0", help="highway-env scenario")
    p.add_argument("--seed", type=int, default=0, help="episode seed")
    p.add_argument("--steps", type=int, default=None, help="steps per rollout")
    p.add_argument("--quick", action="store_true", help="short form (tests): fewer steps")
    p.add_argument("--out", type=Path, default=Path("outputs/tutorials") / NAME)
    args = p.parse_args(argv)
    args.steps = args.steps or (9 if args.quick else 30)
    args.branch_horizon = 4 if args.quick else 10
    return args


def main(argv: list[str] | None = None) -> None:
    """Part 1 (reward), part 2 (vehicle class), and their pictures."""
    args = parse_args(argv)
    t_start = time.perf_counter()
    torch.manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    print("== part 1: a custom reward ==")
    rollout, rewards = custom_reward_demo(args)
    print("\n== part 2: a custom vehicle class ==")
    patience, stuck = custom_vehicle_demo(args)
    paths = {
        "reward components": args.out / "reward_components.png",
        "patience": args.out / "patience.png",
    }
    plot_reward_components(rollout, rewards, paths["reward components"])
    plot_patience(patience, stuck, paths["patience"])
    print("\npictures:")
    for label, path in paths.items():
        print(f"  {label:<18} {path}")
    print(f"done in {time.perf_counter() - t_start:.1f} s")


if __name__ == "__main__":
    main()
