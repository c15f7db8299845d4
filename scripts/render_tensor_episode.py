"""An episode simulated by TensorHighwayEnv, drawn by highway-env's own renderer, as a GIF.

The worlds never run in highway-env: each step's tensor state goes through the bridge
(``state_to_highway``) into a HighwayEnv that only draws it.

    python scripts/render_tensor_episode.py --policy rule --seed 3 \
        --out docs/img/sim/tensor_episode.gif
"""

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

from torchrl_grpo.envs import TensorHighwayEnv
from torchrl_grpo.modules import KinematicsLayout, make_scripted_policy
from torchrl_grpo.training.run_plots import save_gif

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("render_tensor_episode")

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--scenario", default="highway-fast-v0")
parser.add_argument("--policy", default="rule", help="a scripted policy (SCRIPTED_POLICIES)")
parser.add_argument("--seed", type=int, default=3)
parser.add_argument("--steps", type=int, default=30)
parser.add_argument("--out", default="outputs/tensor_episode.gif")
args = parser.parse_args()

env = TensorHighwayEnv(args.scenario, num_envs=1, seed=args.seed, return_state=True)
policy = make_scripted_policy(args.policy, KinematicsLayout.from_highway_config(env.config))
with torch.no_grad():
    data = env.rollout(args.steps, policy, break_when_any_done=True)
states = torch.cat([data[:, :1].get("state"), data.get(("next", "state"))], 1)[0]
frames = env.render_frames(states)
video = torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2).contiguous()
path = save_gif(video, Path(args.out))
crashed = bool(data.get(("next", "crashed")).any())
log.info("%d steps (crashed: %s), %d frames: %s", data.shape[1], crashed, len(frames), path)
