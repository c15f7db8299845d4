"""The cost of GRPOLoss's value checks: ``check_values=True`` against ``False``.

Same actor and ``[R, G, T]`` batch as ``bench_loss.py`` (a highway-env-sized
Categorical MLP), forward + backward, the two losses interleaved. The checks look
for NaN / inf in the advantage and the behaviour, reference and policy log-probs of
the valid steps (one device synchronisation). The claim: they cost at most 5% of a
forward + backward in the default configuration; a masked batch is printed too.

Run: ``python benchmarks/bench_loss_checks.py`` (``--help`` for the sizes).
"""

from __future__ import annotations

import torch
from bench_loss import make_actor, make_batch, parse_sizes, time_pair
from claims import claim

from torchrl_grpo.objectives import GRPOLoss

GOAL = 1.05


def main() -> None:
    args = parse_sizes(__doc__.splitlines()[0])
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
