"""The cost of GRPOLoss's value checks: ``check_values=True`` against ``False``.

Same actor and ``[R, G, T]`` batch as ``bench_loss.py`` (a highway-env-sized
Categorical MLP), forward + backward, the two losses interleaved. The checks look
for NaN / inf in the advantage and the behaviour, reference and policy log-probs of
the valid steps (one device synchronisation). The claim: they cost at most 5% of a
forward + backward in the default configuration; a masked batch is printed too.

Run: ``python benchmarks/bench_loss_checks.py`` (``--help`` for the sizes).
"""

from __future__ import annotations

import argparse
import warnings

import torch
from bench_loss import make_actor, make_batch, time_pair
from claims import claim

from torchrl_grpo.objectives import GRPOLoss

GOAL = 1.05


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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

    actor = make_actor()
    shape = (args.roots, args.branches, args.steps)
    print(f"batch {list(shape)}, torch threads {torch.get_num_threads()}")
    ratios = {}
    for masked in (False, True):
        td = make_batch(actor, *shape, masked=masked)
        on, off = GRPOLoss(actor), GRPOLoss(actor, check_values=False)
        t_on, t_off = time_pair(on, off, td, args.reps)
        what = "masked batch" if masked else "full batch  "
        ratios[masked] = t_on / t_off
        print(
            f"{what}  checks on {t_on * 1e3:7.3f} ms   off {t_off * 1e3:7.3f} ms   "
            f"ratio {t_on / t_off:.3f}"
        )
    claim("GRPOLoss checks on / off, forward + backward", ratios[False], f"<={GOAL}")
    claim("GRPOLoss checks on / off, masked batch", ratios[True])


if __name__ == "__main__":
    main()
