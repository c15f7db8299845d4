"""Would a support gate (SPIBB) make a trained learner safer? An offline check.

Usage: ``python benchmarks/lab/bench_support_gate.py <run> [--gates 0.3:1 1.0:5] [--episodes 10]``

Safe policy improvement with baseline bootstrapping (SPIBB, Laroche et al. 2019) keeps
the base policy's action wherever the data compared actions too rarely. This script
applies that rule, after training, to a run that learned with ``model=scene`` or
``model.prior`` and replayed groups (``algo.replay_groups``): the learner acts in a
state only when at least ``k`` of the replay's root states lie within ``r`` of it in
:class:`~torchrl_grpo.modules.scene_features.SceneFeatures` space (Euclidean distance); elsewhere
the
rule policy acts. It evaluates the greedy policy on the evaluation seeds for each gate
``r:k`` beside the two ends: the learner everywhere and the rule policy everywhere.

A gate that helps would keep the learner's gains (return above the rule policy's) and
drop its crashes towards the rule policy's; one that only interpolates between the two
ends says that support, measured this way, does not tell good deviations from bad ones.
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.modules.scene_features import SceneFeatures
from torchrl_grpo.training import load_checkpoint
from torchrl_grpo.training.algos.grpo import make_replay  # the buffer the run trained with
from torchrl_grpo.training.env_builder import make_env, make_layout
from torchrl_grpo.training.evaluation import evaluate
from torchrl_grpo.training.model_builder import make_base_policy, make_policy


class SupportGate(nn.Module):
    """The learner's logits where ``k`` replayed roots lie within ``r``, else the base's action.

    Args:
        learner: observation -> logits (the trained network, prior included).
        base: observation -> int64 actions (the rule policy).
        features: observation -> feature vectors (scene features).
        roots: ``[N, F]`` features of the replay's root states.
        radius: ``r``.
        count: ``k``.
        n_actions: number of discrete actions.
    """

    def __init__(
        self,
        learner: nn.Module,
        base: nn.Module,
        features: nn.Module,
        roots: torch.Tensor,
        radius: float,
        count: int,
        n_actions: int,
    ) -> None:
        super().__init__()
        self.learner, self.base, self.features = learner, base, features
        self.roots, self.radius, self.count, self.n_actions = roots, radius, count, n_actions
        self.supported = 0
        self.states = 0

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """Maps ``[*batch, V, F]`` observations to ``[*batch, n_actions]`` logits."""
        logits = self.learner(observation)
        feats = self.features(observation).reshape(-1, self.roots.shape[1])
        near = (torch.cdist(feats, self.roots) <= self.radius).sum(-1)
        ok = (near >= self.count).reshape(observation.shape[:-2])
        self.supported += int(ok.sum())
        self.states += ok.numel()
        # A margin no trained logit reaches: the base policy's action is the greedy one.
        margin = logits.detach().abs().max() + 10.0
        base = nn.functional.one_hot(self.base(observation), self.n_actions) * margin
        return torch.where(ok.unsqueeze(-1), logits, base.to(logits.dtype))


def load_run(run: Path) -> tuple[DictConfig, EnvBase, ProbabilisticActor, torch.Tensor, int]:
    """The config, its env, the trained policy, replayed observations and frames of a run."""
    ckpt = load_checkpoint(run / "last.pt")
    cfg = OmegaConf.create(ckpt["config"])
    replay = make_replay(cfg.algo)
    if replay is None or ckpt.get("replay") is None:
        raise SystemExit(f"{run} has no replayed groups: train it with algo.replay_groups")
    replay.load_state_dict(ckpt["replay"])
    env = make_env(cfg.env, seed=0)
    policy = make_policy(cfg.model, env)
    policy.load_state_dict(ckpt["policy"])
    return cfg, env, policy, replay[:]["observation"], int(ckpt["frames"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run folder holding last.pt")
    parser.add_argument("--gates", nargs="+", default=["0.3:1", "0.5:1", "1.0:5"], help="r:k pairs")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=10000)
    args = parser.parse_args()
    cfg, env, trained, observations, frames = load_run(args.run)
    features = SceneFeatures(make_layout(env))
    base = make_base_policy("rule", env, "the gate's base policy").module
    learner = trained.module[0].module
    with torch.no_grad():
        roots = torch.unique(features(observations), dim=0)
    print(f"{args.run}: {frames} frames, {len(roots)} distinct replayed root states")
    gates = [(float("inf"), 1, "learner everywhere"), (0.0, 2**62, "rule policy everywhere")]
    for text in args.gates:
        r, k = text.split(":")
        gates.append((float(r), int(k), f"gate r={r} k={k}"))
    for radius, count, label in gates:
        policy = copy.deepcopy(trained)
        gate = SupportGate(learner, base, features, roots, radius, count, int(env.action_spec.n))
        policy.module[0].module = gate
        result, _ = evaluate(
            env,
            policy,
            episodes=args.episodes,
            seed=args.seed,
            max_steps=int(cfg.env.max_episode_steps),
        )
        summary = result.summary()
        print(
            f"  {label:<24} return {summary['return']:6.2f}  crashes "
            f"{summary['crash_rate']:5.1%}  speed {summary['speed']:5.1f} m/s  learner acts in "
            f"{gate.supported}/{gate.states} states"
        )


if __name__ == "__main__":
    main()
