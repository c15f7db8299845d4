"""GRPOLoss forward + backward against ClipPPOLoss forward + backward.

Same actor (a highway-env-sized Categorical MLP: 5x5 kinematics observation, the 5
DiscreteMetaAction actions), same ``[R, G, T]`` batch, same advantage. The claim:
GRPOLoss costs at most 1.2x ClipPPOLoss in its default configuration (critic-free,
no KL). Configurations with a KL term run the reference policy too and are printed
for information only.

Run: ``python benchmarks/bench_loss.py`` (``--help`` for the sizes).
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import torch
from claims import claim
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ClipPPOLoss

from torchrl_grpo.objectives import GRPOLoss

GOAL = 1.2
OBS_DIM, N_ACTIONS, HIDDEN = 25, 5, 64


def make_actor() -> ProbabilisticActor:
    net = nn.Sequential(
        nn.Linear(OBS_DIM, HIDDEN),
        nn.Tanh(),
        nn.Linear(HIDDEN, HIDDEN),
        nn.Tanh(),
        nn.Linear(HIDDEN, N_ACTIONS),
    )
    module = TensorDictModule(net, ["observation"], ["logits"])
    return ProbabilisticActor(
        module, ["logits"], distribution_class=torch.distributions.Categorical, return_log_prob=True
    )


def make_batch(actor: ProbabilisticActor, R: int, G: int, T: int, masked: bool) -> TensorDict:
    td = TensorDict({"observation": torch.randn(R, G, T, OBS_DIM)}, batch_size=[R, G, T])
    with torch.no_grad():
        td = actor(td)
    td["action_log_prob"] = td["action_log_prob"] + 0.1 * torch.randn(R, G, T)
    td["advantage"] = torch.randn(R, G, T, 1)
    td["group_id"] = torch.arange(R).view(R, 1, 1).expand(R, G, T).clone()
    td["branch"] = torch.arange(G).view(1, G, 1).expand(R, G, T).clone()
    if masked:
        lengths = torch.randint(T // 2, T + 1, (R, G, 1))
        td["mask"] = torch.arange(T) < lengths
    else:
        td["mask"] = torch.ones(R, G, T, dtype=torch.bool)
    return td.detach()


def step(loss: torch.nn.Module, td: TensorDict) -> None:
    out = loss(td)
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    total.backward()
    loss.zero_grad(set_to_none=True)


def time_pair(a, b, td: TensorDict, reps: int, warmup: int = 5) -> tuple[float, float]:
    """Median seconds of ``a`` and ``b``, interleaved so that machine noise hits both."""
    for _ in range(warmup):
        step(a, td)
        step(b, td)
    times: dict[int, list[float]] = {0: [], 1: []}
    losses = (a, b)
    for rep in range(reps):
        # alternate which loss runs first: caches and frequency scaling favour neither
        for which in (0, 1) if rep % 2 == 0 else (1, 0):
            t0 = time.perf_counter()
            step(losses[which], td)
            times[which].append(time.perf_counter() - t0)
    return statistics.median(times[0]), statistics.median(times[1])


def parse_sizes(description: str) -> argparse.Namespace:
    """The batch sizes, repetitions, seed and threads of a loss benchmark, applied to torch."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--roots", type=int, default=16, help="R, roots per batch")
    parser.add_argument("--branches", type=int, default=8, help="G, branches per root")
    parser.add_argument("--steps", type=int, default=40, help="T, steps per branch")
    parser.add_argument("--reps", type=int, default=100, help="timed repetitions")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads; 1 is steadier on a shared machine"
    )
    args = parser.parse_args()
    warnings.filterwarnings("ignore", category=UserWarning)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    return args


def main() -> None:
    args = parse_sizes(__doc__.splitlines()[0])
    actor = make_actor()
    td = make_batch(actor, args.roots, args.branches, args.steps, masked=False)
    ppo = ClipPPOLoss(actor, None, critic_coeff=None)
    shape = f"[{args.roots}, {args.branches}, {args.steps}]"
    print(f"batch {shape} = {td.numel()} steps, torch threads {torch.get_num_threads()}")

    t_grpo, t_ppo = time_pair(GRPOLoss(actor), ppo, td, args.reps)
    ratio = t_grpo / t_ppo
    print(f"ClipPPOLoss           fwd+bwd {t_ppo * 1e3:7.2f} ms")
    print(f"GRPOLoss (default)    fwd+bwd {t_grpo * 1e3:7.2f} ms")

    info = {
        "GRPOLoss grpo agg.": (GRPOLoss(actor, aggregation="grpo"), td),
        "GRPOLoss k3 KL": (GRPOLoss(actor, kl_to_ref_coeff=0.04), td),
        "GRPOLoss masked batch": (
            GRPOLoss(actor),
            make_batch(actor, args.roots, args.branches, args.steps, masked=True),
        ),
    }
    for name, (loss, batch) in info.items():
        t_loss, t_ref = time_pair(loss, ppo, batch, max(args.reps // 2, 10))
        print(f"{name:<21} fwd+bwd {t_loss * 1e3:7.2f} ms  ({t_loss / t_ref:.2f}x PPO, info)")

    claim("GRPOLoss / ClipPPOLoss, forward + backward", ratio, f"<={GOAL}")


if __name__ == "__main__":
    main()
