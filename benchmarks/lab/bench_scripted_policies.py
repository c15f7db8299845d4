"""Mean return and crash rate of scripted policies on highway-fast-v0 (default config)."""

import argparse
import logging
import time

import highway_env  # noqa: F401  (registers the scenarios)
import torch
from torchrl.envs import GymEnv

from torchrl_grpo.modules import KinematicsLayout, make_scripted_policy

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("measure")

p = argparse.ArgumentParser()
p.add_argument("--policies", nargs="+", default=["idle", "slower", "random", "rule"])
p.add_argument("--episodes", type=int, default=10)
p.add_argument("--env", default="highway-fast-v0")
args = p.parse_args()

env = GymEnv(args.env, categorical_action_encoding=True)
layout = KinematicsLayout.from_highway_config(env.unwrapped.config)
for name in args.policies:
    kwargs = {"seed": 0} if name == "random" else {}
    policy = make_scripted_policy(name, layout, **kwargs)
    rets, crashes, lens, actions = [], [], [], torch.zeros(5)
    t0 = time.time()
    for seed in range(args.episodes):
        td0 = env.reset(seed=seed)
        td = env.rollout(
            1000, policy=policy, auto_reset=False, tensordict=td0, break_when_any_done=True
        )
        rets.append(td["next", "reward"].sum().item())
        crashes.append(bool(td["next", "terminated"][-1].item()))
        lens.append(td.shape[0])
        actions += torch.bincount(td["action"], minlength=5)
    rets_t = torch.tensor(rets)
    log.info(
        "%-12s return %.2f +- %.2f  crash %.0f%%  len %.1f  actions %s  (%.1fs)",
        name,
        rets_t.mean(),
        rets_t.std(),
        100 * sum(crashes) / len(crashes),
        sum(lens) / len(lens),
        (actions / actions.sum()).numpy().round(2),
        time.time() - t0,
    )
    log.info("  returns %s", [round(r, 2) for r in rets])
