"""Where a run with a crash head and a margin still crashes: a wrong head, or a lost state.

A run trained with ``model.crash_head=true`` and driven with ``model.crash_margin=m``
never takes an action that its head finds more than ``m`` likelier to crash than SLOWER,
the head's labels being "this action, then always-SLOWER to the branch's end"
(``algo.crash_head_tail``). Its crashes then come from one of two places, which this
script tells apart on every crashed episode:

* **the head was wrong**: at some step the action taken, followed by always-SLOWER,
  crashes, while always-SLOWER from that step does not. The head rated the action at
  most ``m`` riskier than SLOWER there; the row gives both of its probabilities;
* **the episode was lost from its start**: always-SLOWER from the first state crashes
  too, as always-SLOWER itself does about once in 5,000 roundabout-v0 episodes.

The step is deterministic, so there is no third case: if always-SLOWER survives from
the first state but not from the crash step, some action in between took the episode
from one to the other, and the last such step is the decisive one.

Each crashed episode is replayed on the tensor simulator in float64 from highway-env's
starts (the simulator follows highway-env to 1e-9 there, docs/sim.md); from every step
before its crash, each of the five actions is branched, then always-SLOWER to the end.

The head sees the observation only. With ``--copies K`` (roundabout-v0), the decisive
step's state is copied K times with the other cars' destinations and IDM exponents
drawn afresh (``hidden_state.redraw_hidden``), and the share of copies in which
the taken action, then always-SLOWER, crashes (and always-SLOWER's) estimates the crash
probability that the observation allows: what a calibrated head would say there. Each
row also says whether the vehicles the ego hit were in the observation at the decisive
step (:func:`partners_seen`), for every other vehicle crashed after the crash step: a
crash with a vehicle the table leaves out is one no head over that observation could
foresee.

    python benchmarks/lab/bench_crash_causes.py --checkpoint <run>/last.pt \\
        --crash-margin 0.001 --episodes 4000 --seed 61000 [--copies 256]
"""

from __future__ import annotations

import argparse
import logging
import warnings
from collections.abc import Callable

import _path  # noqa: F401  (benchmarks/ on sys.path)
import torch
from hidden_state import observed_vehicles, redraw_hidden
from omegaconf import OmegaConf
from tensordict import TensorDict

import torchrl_grpo.experimental  # noqa: F401  (runs of algo=grpo_lab load too)
from torchrl_grpo.envs import TensorHighwayEnv, tensor_params
from torchrl_grpo.envs.core.snapshot_env import STATE_KEY
from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.training import load_run_policy, make_env
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.model_builder import set_crash_margin
from torchrl_grpo.training.transfer import tensor_episodes

warnings.filterwarnings("ignore")
log = logging.getLogger(__name__)

SLOWER, N_ACTIONS = 4, 5


@torch.no_grad()
def branch_crashes(
    env_cfg,
    states: TensorDict,
    first: torch.Tensor,
    count_steps: bool = False,
    native: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, int]:
    """Whether each state, after its ``first`` action and always-SLOWER, crashes: ``[N]``.

    With ``count_steps``, also the number of steps the branches took (their frames);
    with ``native``, the substeps run in C++ (the same model, to an ulp in float64).
    """
    n = states.batch_size[0]
    env = TensorHighwayEnv(
        str(env_cfg.scenario), env_overrides(env_cfg), num_envs=n, dtype=torch.float64,
        native=native,
    )  # fmt: skip
    td = env.reset(TensorDict({STATE_KEY: states}, batch_size=[n]), set_state=True)
    crashed = torch.zeros(n, dtype=torch.bool)
    live = torch.ones(n, dtype=torch.bool)
    action = first.clone()
    steps = 0
    for _ in range(int(env_cfg.max_episode_steps)):
        steps += int(live.sum())
        out = env.step(td.set("action", action))
        crashed |= live & out.get(("next", "crashed")).reshape(n)
        live &= ~out.get(("next", "done")).reshape(n)
        if not live.any():
            break
        td = out.get("next").exclude("reward", "done", "terminated", "truncated", "crashed")
        action = torch.full_like(action, SLOWER)
    return (crashed, steps) if count_steps else crashed


def partners_seen(env_cfg, state: TensorDict, partners: list[int]) -> list[bool]:
    """Whether each of ``partners`` (vehicle rows) is in the observation at ``state``
    (``hidden_state.observed_vehicles``)."""
    scenario, config = str(env_cfg.scenario), env_overrides(env_cfg)
    seen = observed_vehicles(state.unsqueeze(0), scenario, config)[0]
    return [bool(seen[partner]) for partner in partners]


def redrawn_shares(env_cfg, state: TensorDict, action: int, copies: int) -> tuple[float, float]:
    """Over ``copies`` redraws of the hidden variables: the crash shares of ``action`` and
    of SLOWER, each followed by always-SLOWER."""
    params = tensor_params(str(env_cfg.scenario), env_overrides(env_cfg))
    redrawn = redraw_hidden(
        state.unsqueeze(0).expand(copies).clone(), params, "both", torch.Generator().manual_seed(0)
    )
    both = torch.cat([redrawn, redrawn])
    first = torch.cat([torch.full((copies,), action), torch.full((copies,), SLOWER)])
    crashed = branch_crashes(env_cfg, both, first).double()
    return float(crashed[:copies].mean()), float(crashed[copies:].mean())


def causes(
    env_cfg,
    policy,
    risk: Callable[[torch.Tensor], torch.Tensor],
    episodes: int,
    seed: int,
    copies: int = 0,
) -> list[dict]:
    """One record per crashed episode: its steps, the branches' outcomes, and ``risk``'s
    crash probabilities (``[T, 5]`` from ``[T, ...]`` float32 observations)."""
    data, before = tensor_episodes(
        env_cfg, policy, episodes=episodes, seed=seed, return_state=True, dtype=torch.float64
    )
    crashed = data.get(("next", "crashed")).reshape(episodes, -1) & before
    records = []
    for e in crashed.any(1).nonzero().squeeze(-1).tolist():
        last = int(crashed[e].nonzero()[0])
        steps = data[e, : last + 1]
        states = steps.get(STATE_KEY)
        t = last + 1
        # Row (k, a): step k's state, action a first, then always-SLOWER.
        outcome = branch_crashes(
            env_cfg,
            states.unsqueeze(1).expand(t, N_ACTIONS).reshape(-1),
            torch.arange(N_ACTIONS).repeat(t),
        ).reshape(t, N_ACTIONS)
        obs = steps.get("observation").float()
        risks = risk(obs)
        taken = steps.get("action")
        if taken.dim() == 2:  # one-hot actions
            taken = taken.argmax(-1)
        decisive = [k for k in range(t) if outcome[k, taken[k]] and not outcome[k, SLOWER]]
        k = decisive[-1] if decisive else None
        shares = None
        if copies and k is not None:
            shares = redrawn_shares(env_cfg, states[k], int(taken[k]), copies)
        # Every other vehicle crashed after the crash step: the ego's partner, or a wreck
        # of two others that it ran into.
        after = data[e, last].get(("next", STATE_KEY)).get("vehicles")
        hit = after.get("crashed") & after.get("present")
        partners = hit[1:].nonzero().squeeze(-1).add(1).tolist()
        seen = None if k is None else partners_seen(env_cfg, states[k], partners)
        records.append(
            {
                "redrawn_shares": shares,
                "partners": partners,
                "partners_seen": seen,
                "episode": seed + e,
                "crash_step": last,
                "actions": taken.tolist(),
                "slower_from_start_crashes": bool(outcome[0, SLOWER]),
                "decisive_step": k,
                "risk_taken": [round(float(risks[j, taken[j]]), 4) for j in range(t)],
                "risk_slower": [round(float(risks[j, SLOWER]), 4) for j in range(t)],
                "safe_actions": [int((~outcome[j]).sum()) for j in range(t)],
                "outcome": outcome.tolist(),
            }
        )
    return records


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="a run's last.pt, with a crash head")
    p.add_argument("--crash-margin", type=float, required=True)
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=61000)
    p.add_argument("--copies", type=int, default=0, help="redraws of the hidden variables")
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    env_cfg = OmegaConf.create(load_checkpoint(args.checkpoint)["config"])["env"]
    policy = load_run_policy(args.checkpoint, env_cfg, make_env(env_cfg, seed=0))
    set_crash_margin(policy, args.crash_margin)
    head = next(m for m in policy.modules() if isinstance(m, CrashHead))
    records = causes(
        env_cfg,
        policy,
        lambda obs: torch.sigmoid(head.crash_logits(obs)),
        args.episodes,
        args.seed,
        args.copies,
    )
    wrong = [r for r in records if r["decisive_step"] is not None]
    lines = [
        f"{env_cfg.scenario}: {args.checkpoint} at crash margin {args.crash_margin}, "
        f"{args.episodes} tensor-simulator episodes (float64) from seed {args.seed}: "
        f"{len(records)} crashed",
        "",
        "| episode | crash step | actions | always-SLOWER from the start | decisive step "
        "| head there: taken / SLOWER | redrawn hidden variables there: taken / SLOWER "
        "| the other crashed vehicles: in the observation there | safe first actions per step |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        k = r["decisive_step"]
        there = "-" if k is None else f"{r['risk_taken'][k]:.4f} / {r['risk_slower'][k]:.4f}"
        shares = r["redrawn_shares"]
        redrawn = "-" if shares is None else f"{shares[0]:.3f} / {shares[1]:.3f}"
        seen = (
            "-"
            if k is None
            else ", ".join(
                f"{p}: {'seen' if s else 'unseen'}"
                for p, s in zip(r["partners"], r["partners_seen"], strict=True)
            )
        )
        lines.append(
            f"| {r['episode']} | {r['crash_step']} | {r['actions']} | "
            f"{'crashes' if r['slower_from_start_crashes'] else 'safe'} | "
            f"{'-' if k is None else k} | {there} | {redrawn} | {seen} | {r['safe_actions']} |"
        )
    lines += [
        "",
        f"the head was wrong (an action it allowed turned a safe state into a crash under "
        f"always-SLOWER): {len(wrong)} of {len(records)}; lost from the start: "
        f"{len(records) - len(wrong)}",
    ]
    print("\n".join(lines))  # noqa: T201 (the benchmark's output)


if __name__ == "__main__":
    main()
