"""How well each policy network can learn to drive: behaviour cloning of the rule policy.

A diagnostic of the ``model`` group, with no RL in it. It drives the rule policy with
``--noise`` random actions (so that the data holds states the rule policy would not
reach alone) for ``--frames`` steps from seeds 0, 1, ...; labels every state with the
rule policy's action; trains each network by cross-entropy on the same data; and
reports, side by side, the accuracy on states of other episodes (seeds 5000..5009) and
the greedy evaluation protocol of ``scripts/evaluate.py`` (episodes from seeds 10000,
10001, ...). A network that cannot imitate the rule policy from these labels cannot
learn its safety margins from the far noisier signal of RL either.

    python benchmarks/bench_features.py --frames 5000 --steps 3000 --episodes 10
"""

import argparse
import logging
import time

import torch
from claims import claim
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import RulePolicy
from torchrl_grpo.training import evaluate, format_table
from torchrl_grpo.training.config import ModelConfig
from torchrl_grpo.training.model_builder import make_policy

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_features")

p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
p.add_argument("--scenario", default="highway-fast-v0")
p.add_argument("--models", nargs="+", default=["mlp", "scene"])
p.add_argument("--frames", type=int, default=5000, help="labelled states to train on")
p.add_argument("--noise", type=float, default=0.2, help="fraction of random actions")
p.add_argument("--steps", type=int, default=3000, help="cross-entropy steps")
p.add_argument("--batch", type=int, default=256)
p.add_argument("--episodes", type=int, default=10)
args = p.parse_args()


def labelled_states(env, rule, seeds, max_frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """States of the rule policy perturbed by random actions, with its own actions."""
    generator = torch.Generator().manual_seed(0)
    observations, labels = [], []
    for seed in seeds:
        env.set_seed(seed)
        td = env.reset()
        while len(labels) < max_frames:
            label = rule(td.clone())["action"]
            observations.append(td["observation"])
            labels.append(label)
            explore = torch.rand((), generator=generator) < args.noise
            random = torch.randint(5, (), generator=generator)
            td["action"] = random if explore else label
            td = env.step(td)["next"]
            if td["done"].item():
                break
        if len(labels) >= max_frames:
            break
    return torch.stack(observations), torch.stack(labels)


env = HighwayEnv(args.scenario, seed=0)
rule = RulePolicy.from_highway_config(env.config)
t0 = time.perf_counter()
x_train, y_train = labelled_states(env, rule, range(100_000), args.frames)
x_test, y_test = labelled_states(env, rule, range(5000, 5010), 10**9)
log.info(
    "%d training states, %d held-out states, %.0f s",
    len(y_train),
    len(y_test),
    time.perf_counter() - t0,
)

results = [evaluate(env, rule, episodes=args.episodes, seed=10_000, name="rule policy")[0]]
accuracy = {}
for kind in args.models:
    torch.manual_seed(0)
    policy = make_policy(OmegaConf.structured(ModelConfig(kind=kind)), env)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    t0 = time.perf_counter()
    for _ in range(args.steps):
        idx = torch.randint(len(y_train), (args.batch,))
        logits = policy(TensorDict(observation=x_train[idx], batch_size=[args.batch]))["logits"]
        loss = torch.nn.functional.cross_entropy(logits, y_train[idx])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        logits = policy(TensorDict(observation=x_test, batch_size=[len(y_test)]))["logits"]
    accuracy[kind] = float((logits.argmax(-1) == y_test).float().mean())
    res, _ = evaluate(env, policy, episodes=args.episodes, seed=10_000, name=f"cloned {kind}")
    results.append(res)
    log.info("%s: held-out accuracy %.3f, %.0f s", kind, accuracy[kind], time.perf_counter() - t0)

log.info("\n%s", format_table(results))
for kind, value in accuracy.items():
    claim(f"{args.scenario}: held-out accuracy of a cloned rule policy, model={kind}", value)
if "mlp" in accuracy and "scene" in accuracy:
    claim(
        f"{args.scenario}: held-out errors of cloned rule policies, scene / mlp",
        (1 - accuracy["scene"]) / max(1 - accuracy["mlp"], 1e-9),
    )
