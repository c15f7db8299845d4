"""How well each policy network can learn to drive: behaviour cloning of a teacher.

A diagnostic of the ``model`` group, with no RL in it. It drives the teacher with
``--noise`` random actions (so that the data holds states the teacher would not
reach alone) for ``--frames`` steps from seeds 0, 1, ...; labels every state with the
teacher's choice; trains each network by cross-entropy on the same data; and reports,
side by side, the agreement on states of other episodes (seeds 5000..5009) and the
greedy evaluation protocol of ``scripts/evaluate.py`` (episodes from seeds 10000,
10001, ...).

The teacher is the rule policy (``--teacher rule``): a network that cannot imitate it
from these labels cannot learn its safety margins from the far noisier signal of RL
either. Or the lookahead planner over the rule policy (``--teacher lookahead``), whose
scores are exactly what the groups of ``algo.first_action=enumerate
algo.tail_policy=rule`` compare: a clone of it is what a GRPO learner on those groups
would become with noiseless groups, and the script says how many labelled states (and
simulated frames) that takes. The planner's label is the set of its best actions
(ties are frequent: the planner breaks them by action index, which a clone need not
copy); a clone agrees where its action is one of them, and its regret is the planner's
best branch return minus that of the clone's action.

    python benchmarks/lab/bench_features.py --frames 5000 --steps 3000 --episodes 10
    python benchmarks/lab/bench_features.py --teacher lookahead --frames 1000 --episodes 30
    python benchmarks/lab/bench_features.py --models scene neighbours  # the lab's network too
"""

import argparse
import logging
import time

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from claims import claim
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.experimental.grpo_lab import GRPOLabModelConfig  # the lab's kinds too
from torchrl_grpo.modules import RulePolicy
from torchrl_grpo.training import evaluate
from torchrl_grpo.training.model_builder import make_policy
from torchrl_grpo.training.results import format_table

logging.basicConfig(level=logging.INFO, format="%(message)s")
log = logging.getLogger("bench_features")

p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
p.add_argument("--scenario", default="highway-fast-v0")
p.add_argument("--models", nargs="+", default=["mlp", "scene"])
p.add_argument("--teacher", choices=["rule", "lookahead"], default="rule")
p.add_argument("--horizon", type=int, default=4, help="the lookahead teacher's branch steps")
p.add_argument("--frames", type=int, default=5000, help="labelled states to train on")
p.add_argument("--noise", type=float, default=0.2, help="fraction of random actions")
p.add_argument("--steps", type=int, default=3000, help="cross-entropy steps")
p.add_argument("--batch", type=int, default=256)
p.add_argument("--episodes", type=int, default=10)
args = p.parse_args()

N_ACTIONS = 5


def teacher_scores(teacher, td) -> torch.Tensor:
    """The teacher's score of every action: branch returns, or 1 on the rule's action."""
    if isinstance(teacher, LookaheadPolicy):
        return teacher.returns(td)
    action = teacher(td.clone())["action"]
    return torch.nn.functional.one_hot(action, N_ACTIONS).double()


def labelled_states(env, teacher, seeds, max_frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """States of the teacher perturbed by random actions, with its scores of every action.

    The teacher drives with the first of its best actions (the planner's own choice).
    """
    generator = torch.Generator().manual_seed(0)
    observations, scores = [], []
    for seed in seeds:
        env.set_seed(seed)
        td = env.reset()
        while len(scores) < max_frames:
            scores.append(teacher_scores(teacher, td))
            observations.append(td["observation"])
            explore = torch.rand((), generator=generator) < args.noise
            random = torch.randint(N_ACTIONS, (), generator=generator)
            td["action"] = random if explore else scores[-1].argmax()
            td = env.step(td)["next"]
            if td["done"].item():
                break
        if len(scores) >= max_frames:
            break
    return torch.stack(observations), torch.stack(scores)


def best_actions(scores: torch.Tensor) -> torch.Tensor:
    """``[N, 5]`` booleans: the actions of highest score in each state."""
    return scores == scores.max(-1, keepdim=True).values


@torch.no_grad()
def greedy(policy, observations: torch.Tensor) -> torch.Tensor:
    """The policy's greedy action in each state."""
    batch = TensorDict(observation=observations, batch_size=[len(observations)])
    return policy(batch)["logits"].argmax(-1)


def agreement(actions: torch.Tensor, scores: torch.Tensor) -> float:
    """Fraction of the states where ``actions`` is one of the teacher's best."""
    return float(best_actions(scores).gather(-1, actions.unsqueeze(-1)).float().mean())


# The planner reads the simulator state that return_state=True writes at every step.
env = HighwayEnv(args.scenario, seed=0, return_state=args.teacher == "lookahead")
teacher = rule = RulePolicy.from_highway_config(env.config)
teacher_name = "rule policy"
if args.teacher == "lookahead":
    teacher = LookaheadPolicy(HighwayEnv(args.scenario), rule, horizon=args.horizon)
    teacher_name = f"lookahead H={args.horizon} over the rule policy"
t0 = time.perf_counter()
x_train, s_train = labelled_states(env, teacher, range(100_000), args.frames)
# Every labelled state costs its trajectory step, plus the planner's branches.
train_frames = len(s_train) + getattr(teacher, "frames", 0)
x_test, s_test = labelled_states(env, teacher, range(5000, 5010), 10**9)
best_train, best_test = best_actions(s_train), best_actions(s_test)
# Cross-entropy against the uniform distribution over the best actions.
target = best_train.double() / best_train.sum(-1, keepdim=True)
log.info(
    "%d training states (%d simulated frames), %d held-out states, %.0f s",
    len(s_train),
    train_frames,
    len(s_test),
    time.perf_counter() - t0,
)
# A network that learned nothing but the commonest choice agrees this often: the floor
# the agreements below are read against.
commonest = best_train.sum(0).argmax()
log.info(
    "states where each action (0..4) is among the teacher's best: %s of %d; several best "
    "actions in %.3f of the held-out states; the commonest action agrees in %.3f",
    best_train.sum(0).tolist(),
    len(s_train),
    float((best_test.sum(-1) > 1).float().mean()),
    agreement(commonest.expand(len(s_test)), s_test),
)

results = [evaluate(env, teacher, episodes=args.episodes, seed=10_000, name=teacher_name)[0]]
if args.teacher != "rule":
    results.append(evaluate(env, rule, episodes=args.episodes, seed=10_000, name="rule policy")[0])
accuracy = {}
for kind in args.models:
    torch.manual_seed(0)
    policy = make_policy(OmegaConf.structured(GRPOLabModelConfig(kind=kind)), env)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    t0 = time.perf_counter()
    for _ in range(args.steps):
        idx = torch.randint(len(s_train), (args.batch,))
        logits = policy(TensorDict(observation=x_train[idx], batch_size=[args.batch]))["logits"]
        loss = torch.nn.functional.cross_entropy(logits, target[idx].to(logits.dtype))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    actions = greedy(policy, x_test)
    accuracy[kind] = agreement(actions, s_test)
    message = "%s: held-out agreement %.3f, training agreement %.3f"
    values = [kind, accuracy[kind], agreement(greedy(policy, x_train), s_train)]
    if args.teacher == "lookahead":
        # What the clone's choices cost by the planner's own scores: ties cost nothing.
        regret = s_test.max(-1).values - s_test.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
        message += ", mean regret %.3f, regret > 0.5 in %.3f of the held-out states"
        values += [float(regret.mean()), float((regret > 0.5).float().mean())]
    log.info(message + ", %.0f s", *values, time.perf_counter() - t0)
    res, _ = evaluate(env, policy, episodes=args.episodes, seed=10_000, name=f"cloned {kind}")
    results.append(res)

log.info("\n%s", format_table(results))
for kind, value in accuracy.items():
    claim(f"{args.scenario}: held-out agreement of a cloned {teacher_name}, model={kind}", value)
if "mlp" in accuracy and "scene" in accuracy:
    claim(
        f"{args.scenario}: held-out disagreements of the cloned {teacher_name}, scene / mlp",
        (1 - accuracy["scene"]) / max(1 - accuracy["mlp"], 1e-9),
    )
