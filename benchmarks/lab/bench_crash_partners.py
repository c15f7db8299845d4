"""What a policy's crashes are made of: who the ego hits, where, and whether it could see it.

Drives ``--episodes`` greedy episodes of a checkpoint's policy (or always-SLOWER, the rule
policy) on the tensor simulator from highway-env's seeds ``--seed``.. and, for every
crash, reads the simulator state of the step before it: the partner (the other vehicle
the step crashed), whether it was ahead of the ego or behind it, in the ego's lane or
beside it, whether the ego or the partner was changing lanes, the ego's speed set-point,
and whether the partner was in the observation the policy acted on (highway-env's
Kinematics: the nearest ``vehicles_count - 1`` vehicles, those more than two lengths
behind left out unless ``see_behind``). A crash by a vehicle the policy could not see is
a crash no network over that observation can learn to avoid from the state alone.

    python benchmarks/lab/bench_crash_partners.py --checkpoint outputs/.../last.pt --episodes 1000
    python benchmarks/lab/bench_crash_partners.py --policy rule --episodes 1000
"""

from __future__ import annotations

import argparse
import logging
from collections import Counter

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from bench_crash_rates import ACTIONS, trained

from torchrl_grpo.modules import make_scripted_policy
from torchrl_grpo.training import compose_config, make_env
from torchrl_grpo.training.transfer import tensor_episodes

logging.basicConfig(level=logging.INFO, format="%(message)s")

#: Who steers to another lane in the crash's step: (the ego, the partner).
MOVERS = {
    (True, True): "both changing",
    (True, False): "ego changing",
    (False, True): "partner changing",
    (False, False): "neither changing",
}
#: highway-env's vehicle length (m): the Kinematics observation keeps vehicles at most
#: two lengths behind the ego when ``see_behind`` is off.
VEHICLE_LENGTH = 5.0


def load(args):
    """The env config and the policy to drive."""
    if args.checkpoint:
        return trained(args.checkpoint)
    env_cfg = compose_config([]).env
    return env_cfg, make_scripted_policy(args.policy, make_env(env_cfg))


def observed(veh, partner: int, count: int, see_behind: bool) -> bool:
    """Whether ``partner`` is among the ``count`` nearest vehicles the ego observes."""
    dx = veh["x"][1:] - veh["x"][0]
    dy = veh["y"][1:] - veh["y"][0]
    distance = torch.hypot(dx, dy)
    eligible = veh["present"][1:] & (see_behind | (dx > -2 * VEHICLE_LENGTH))
    distance = torch.where(eligible, distance, torch.full_like(distance, float("inf")))
    nearest = distance.argsort()[:count]
    return bool(((nearest + 1) == partner).any() & eligible[partner - 1])


def describe(before, after, action: int, count: int, see_behind: bool, lane_width: float) -> dict:
    """The crash of one step: its partner and the geometry of the step before."""
    veh, nxt = before["vehicles"], after["vehicles"]
    others = nxt["crashed"][1:] & ~veh["crashed"][1:]
    if not bool(others.any()):
        return {"partner": "none (off-road or a vehicle already crashed)"}
    dist = torch.hypot(veh["x"][1:] - veh["x"][0], veh["y"][1:] - veh["y"][0])
    dist = torch.where(others, dist, torch.full_like(dist, float("inf")))
    partner = int(dist.argmin()) + 1
    dx = float(veh["x"][partner] - veh["x"][0])
    side = abs(float(veh["y"][partner] - veh["y"][0])) >= lane_width / 2
    # The lane each vehicle steers to during the crash's step (the ego's action of that
    # step and the others' MOBIL decisions included), against the lane it started in.
    ego_changing = int(nxt["target_lane"][0]) != int(veh["lane"][0])
    partner_changing = int(nxt["target_lane"][partner]) != int(veh["lane"][partner])
    return {
        "partner": "ahead" if dx > 0 else "behind",
        "lane": "beside" if side else "same lane",
        "mover": MOVERS[(ego_changing, partner_changing)],
        "ego set-point": f"{float(veh['target_speed'][0]):.0f} m/s",
        "ego action": ACTIONS[action],
        "seen": "seen" if observed(veh, partner, count, see_behind) else "not seen",
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", help="a run's last.pt (else --policy)")
    p.add_argument("--policy", default="rule", help="a scripted policy without --checkpoint")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=30_000)
    args = p.parse_args()
    env_cfg, policy = load(args)
    obs_cfg = dict(env_cfg.config).get("observation", {}) or {}
    count = int(obs_cfg.get("vehicles_count", 5)) - 1
    see_behind = bool(obs_cfg.get("see_behind", False))
    lane_width = 4.0
    data, before = tensor_episodes(
        env_cfg, policy, episodes=args.episodes, seed=args.seed, return_state=True
    )
    hits = data.get(("next", "crashed")).reshape(args.episodes, -1) & before
    rows = []
    for i in hits.any(1).nonzero().squeeze(-1).tolist():
        t = int(hits[i].float().argmax())
        step = data[i, t]
        action = int(step.get("action").reshape(-1)[0])
        rows.append(
            describe(step["state"], step["next", "state"], action, count, see_behind, lane_width)
        )
    name = args.checkpoint or args.policy
    print(f"{name}: {len(rows)} crashes in {args.episodes} episodes")
    for key in ("partner", "lane", "mover", "ego action", "ego set-point", "seen"):
        tally = Counter(r[key] for r in rows if key in r)
        print(f"  {key}: " + ", ".join(f"{k} {v}" for k, v in tally.most_common()))
    combos = Counter(
        f"{r['partner']}/{r['lane']}/{r['mover']}/{r['seen']}" for r in rows if "lane" in r
    )
    print("  by kind: " + "; ".join(f"{k} {v}" for k, v in combos.most_common(8)))


if __name__ == "__main__":
    main()
