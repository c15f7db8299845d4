"""Would a support gate (SPIBB) make a trained learner safer? An offline check.

Usage: ``python benchmarks/bench_support_gate.py <run> [--gates 0.3:1 1.0:5] [--episodes 10]``

Safe policy improvement with baseline bootstrapping (SPIBB, Laroche et al. 2019) keeps
the base policy's action wherever the data compared actions too rarely. This script
applies that rule, after training, to a run that learned with ``model=scene`` or
``model.prior`` and replayed groups (``algo.replay_groups``): the learner acts in a
state only when at least ``k`` of the replay's root states lie within ``r`` of it in
:class:`~torchrl_grpo.modules.SceneFeatures` space (Euclidean distance); elsewhere the
rule policy acts. It evaluates the greedy policy on the evaluation seeds for each gate
``r:k`` beside the two ends: the learner everywhere and the rule policy everywhere.

A gate that helps would keep the learner's gains (return above the rule policy's) and
drop its crashes towards the rule policy's; one that only interpolates between the two
ends says that support, measured this way, does not tell good deviations from bad ones.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from torch import nn

from torchrl_grpo.modules import SceneFeatures
from torchrl_grpo.training import Trainer
from torchrl_grpo.training.config import register_configs
from torchrl_grpo.training.env_builder import make_env, make_layout
from torchrl_grpo.training.evaluation import evaluate
from torchrl_grpo.training.model_builder import make_base_policy

ROOT = Path(__file__).resolve().parent.parent


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


def load_run(run: Path) -> Trainer:
    """The run's trainer, resumed from its ``last.pt`` (policy and replay)."""
    overrides = [
        line[2:].strip()
        for line in (run / ".hydra" / "overrides.yaml").read_text().splitlines()
        if line.startswith("- ") and not line[2:].startswith(("experiment.out_dir", "logger"))
    ]
    scratch = tempfile.mkdtemp(prefix="support_gate_")
    register_configs()
    with initialize_config_dir(str(ROOT / "conf"), version_base=None):
        cfg = compose(
            "config",
            overrides=[
                *overrides,
                f"resume={run / 'last.pt'}",
                "logger=none",
                f"experiment.out_dir={scratch}",
            ],
        )
    trainer = Trainer(cfg, run_dir=scratch)
    if trainer.replay is None or len(trainer.replay) == 0:
        raise SystemExit(f"{run} has no replayed groups: train it with algo.replay_groups")
    return trainer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run folder holding last.pt")
    parser.add_argument("--gates", nargs="+", default=["0.3:1", "0.5:1", "1.0:5"], help="r:k pairs")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=10000)
    args = parser.parse_args()
    trainer = load_run(args.run)
    cfg = trainer.cfg
    env = make_env(cfg.env, seed=0)
    features = SceneFeatures(make_layout(env))
    base = make_base_policy("rule", env, "the gate's base policy").module
    learner = trainer.policy.module[0].module
    with torch.no_grad():
        roots = torch.unique(features(trainer.replay[:]["observation"]), dim=0)
    print(f"{args.run}: {trainer.frames} frames, {len(roots)} distinct replayed root states")
    gates = [(float("inf"), 1, "learner everywhere"), (0.0, 2**62, "rule policy everywhere")]
    for text in args.gates:
        r, k = text.split(":")
        gates.append((float(r), int(k), f"gate r={r} k={k}"))
    for radius, count, label in gates:
        policy = copy.deepcopy(trainer.policy)
        gate = SupportGate(learner, base, features, roots, radius, count, 5)
        policy.module[0].module = gate
        result, _ = evaluate(
            env,
            policy,
            episodes=args.episodes,
            seed=args.seed,
            max_steps=int(cfg.env.max_episode_steps),
        )
        crashes = sum(result.crashed) / len(result.crashed)
        print(
            f"  {label:<24} return {statistics.mean(result.returns):6.2f}  crashes "
            f"{crashes:5.1%}  speed {statistics.mean(result.speeds):5.1f} m/s  learner acts in "
            f"{gate.supported}/{gate.states} states"
        )


if __name__ == "__main__":
    main()
