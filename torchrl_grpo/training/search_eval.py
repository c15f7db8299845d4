"""Test-time search over a trained policy, with all of an evaluation's episodes at once.

:func:`evaluate_search` evaluates the lookahead planner of
:func:`~torchrl_grpo.training.search_policy` (every action tried, then ``horizon - 1``
steps of the policy's greedy actions) with
:func:`~torchrl_grpo.branching.batched_search.search_episodes`: the episodes step in
lock-step and, at every step, all live episodes' branches are the rows of one rollout of
the tensor simulator. Same episodes, actions and returns as the planner deciding one
state at a time (``tests/branching/test_batched_search.py``), a fraction of the time
(``benchmarks/bench_lookahead.py``).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import signal
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Literal

import torch
from omegaconf import DictConfig
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from torchrl_grpo.branching.batched_search import search_episodes
from torchrl_grpo.branching.lookahead import LookaheadPolicy
from torchrl_grpo.envs.highway.tensor_env import TensorHighwayEnv
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training.env_builder import env_overrides, make_env, tensor_covers
from torchrl_grpo.training.results import EvalResult

__all__ = ["PLAN_DTYPE", "evaluate_search", "is_stochastic", "search_policy", "searched_result"]

log = logging.getLogger(__name__)

#: Where the searched episodes run: highway-env itself (lock-step envs whose states are
#: imported into the planner in one batch per step) or the tensor simulator's worlds.
EpisodesOn = Literal["highway", "tensor"]

#: The planner's float dtype by where the episodes run. highway-env computes in float64,
#: and the tensor simulator in float64 follows it to 1e-9 (docs/sim.md, parity): a
#: float32 planner's branches drift from the episode it drives, most on the roundabout's
#: ring, where the search over always-SLOWER crashed in 27 of 1,000 highway-env episodes
#: planning in float32 and in none in float64 (docs/lab/scenarios.md). On the tensor
#: simulator the planner takes the episodes' own dtype, training's float32.
PLAN_DTYPE: dict[str, torch.dtype] = {"highway": torch.float64, "tensor": torch.float32}


def is_stochastic(policy: TensorDictModuleBase) -> bool:
    """Whether ``policy`` samples (an actor with a distribution): wrap it to act greedily.

    Example:
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> is_stochastic(ConstantActionPolicy("SLOWER"))
        False
    """
    return hasattr(policy, "get_dist") or any(
        hasattr(m, "get_dist") for m in policy.modules() if m is not policy
    )


def search_policy(
    env_cfg: DictConfig,
    policy: TensorDictModuleBase,
    horizon: int,
    dtype: torch.dtype = PLAN_DTYPE["highway"],
) -> LookaheadPolicy:
    """The lookahead planner over a trained policy's greedy actions: test-time search.

    From every state, each action is tried and followed by ``horizon - 1`` steps of
    ``policy``'s greedy actions; the action whose branch earns the most is played
    (:class:`~torchrl_grpo.branching.LookaheadPolicy`, the ``lookahead`` baseline's
    planner with the trained policy in place of the rule policy). Where the tensor
    simulator covers the scenario, the branches are rows of one of its rollouts, from
    the driven highway-env state imported through the bridge: five times faster than
    highway-env's own snapshots at H = 8, with the same returns
    (``benchmarks/bench_lookahead.py --checkpoint``); elsewhere they run on highway-env
    snapshots. The env it drives must be built with ``return_state=True``.

    Args:
        env_cfg: the ``env`` config group the policy was trained on.
        policy: the trained actor.
        horizon: steps per branch (>= 1).
        dtype: the tensor simulator's float dtype for the branches: highway-env's float64
            by default, so that a branch predicts the driven episode exactly (:data:`PLAN_DTYPE`).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.modules import make_scripted_policy
        >>> cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}})
        >>> from torchrl_grpo.training.evaluation import evaluate
        >>> planner = search_policy(cfg, make_scripted_policy("slower"), horizon=2)
        >>> res, _ = evaluate(make_env(cfg, return_state=True), planner, episodes=1, seed=0,
        ...                   max_steps=3)
        >>> type(planner.env).__name__, res.lengths, planner.frames <= 3 * 5 * 2
        ('TensorHighwayEnv', [3], True)
    """
    if isinstance(policy, TensorDictModuleBase) and is_stochastic(policy):
        policy = DeterministicActor(policy)
    highway = make_env(env_cfg)
    if not tensor_covers(env_cfg):
        return LookaheadPolicy(highway, policy, horizon=horizon)
    # One row per action of the one state planned at a time.
    rows = int(highway.action_spec.n)
    scenario, overrides = str(env_cfg.scenario), env_overrides(env_cfg)
    sim = TensorHighwayEnv(scenario, overrides, num_envs=rows, seed=0, dtype=dtype)
    return LookaheadPolicy(sim, policy, horizon=horizon, import_state=sim.state_from_highway)


def evaluate_search(
    env_cfg: DictConfig,
    policy: TensorDictModuleBase,
    horizon: int,
    *,
    episodes: int,
    seed: int,
    max_steps: int = 1000,
    name: str = "search",
    on: EpisodesOn = "highway",
    dtype: torch.dtype | None = None,
    workers: int = 1,
    progress: bool = False,
) -> EvalResult:
    """The lookahead planner over ``policy``, episodes ``seed, seed + 1, ...`` all at once.

    Episode ``i`` is the one :func:`~torchrl_grpo.training.evaluate` plays from
    ``seed + i`` with :func:`~torchrl_grpo.training.search_policy` (on highway-env), with
    the same actions and returns; the episodes advance together and each step plans all live
    episodes in one rollout of ``episodes x n_actions`` rows of the tensor simulator.

    Args:
        env_cfg: the ``env`` config group (the tensor simulator must cover it).
        policy: the policy the branches follow after their first action (a learned actor
            acts greedily).
        horizon: steps per branch (>= 1).
        episodes: how many episodes.
        seed: the first episode's seed.
        max_steps: cap on an episode's length.
        name: the label in the results.
        on: ``"highway"``: the episodes run on highway-env (the evaluation's reference),
            their states imported into the planner in one batch per step; ``"tensor"``:
            they are worlds of the tensor simulator, started where highway-env's
            episodes start (as :func:`~torchrl_grpo.training.transfer.evaluate_on_tensor`
            starts them).
        dtype: the tensor simulator's float dtype, the planner's (and the episodes' with
            ``on="tensor"``); default :data:`PLAN_DTYPE` of ``on``: float64 for
            highway-env's episodes, training's float32 for the tensor simulator's.
        workers: forked processes, each playing a contiguous share of the episodes with
            one thread (the same results as one process, episode for episode).
        progress: a tqdm bar over the steps (of the first worker's share).

    Raises:
        ValueError: a scenario or config the tensor simulator does not cover, fewer than
            one episode, or an unknown ``on``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.modules import make_scripted_policy
        >>> cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}})
        >>> res = evaluate_search(cfg, make_scripted_policy("slower"), 2, episodes=2, seed=0,
        ...                       max_steps=3, on="tensor")
        >>> res.lengths, res.seeds
        ([3, 3], [0, 1])
    """
    if on not in ("highway", "tensor"):
        raise ValueError(f"on must be 'highway' or 'tensor', got {on!r}")
    if not tensor_covers(env_cfg):
        raise ValueError(
            f"evaluate_search plans on the tensor simulator, which does not cover "
            f"{env_cfg.scenario} with config {env_overrides(env_cfg)}: use "
            "evaluate(..., search_policy(...)) there"
        )
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if is_stochastic(policy):
        policy = DeterministicActor(policy)
    seeds = [int(seed) + i for i in range(episodes)]
    workers = max(1, min(int(workers), episodes))
    if workers > 1 and "fork" not in mp.get_all_start_methods():
        workers = 1
    job = (env_cfg, policy, int(horizon), int(max_steps), on, dtype or PLAN_DTYPE[on], name)
    if workers == 1:
        outs = [_play(job, seeds, progress)]
    else:
        outs = _forked(job, seeds, workers, progress)
    return searched_result(name, torch.cat(outs), seeds)


def _play(job: tuple, seeds: list[int], progress: bool = False) -> TensorDict:
    """The episodes of ``seeds`` in lock-step, with a planner of one row per action of each."""
    env_cfg, policy, horizon, max_steps, on, dtype, name = job
    scenario, overrides = str(env_cfg.scenario), env_overrides(env_cfg)
    n_actions = 5  # the tensor simulator's DiscreteMetaAction
    sim = TensorHighwayEnv(
        scenario, overrides, num_envs=n_actions * len(seeds), seed=0, dtype=dtype
    )
    if on == "highway":
        planner = LookaheadPolicy(sim, policy, horizon, import_state=sim.state_from_highway)
        episodes = [make_env(env_cfg, return_state=True) for _ in seeds]
    else:
        planner = LookaheadPolicy(sim, policy, horizon)
        episodes = TensorHighwayEnv(
            scenario, overrides, num_envs=len(seeds), seed=0, return_state=True, dtype=dtype
        )
    if not progress:
        out = search_episodes(planner, episodes, seeds, max_steps)
    else:
        bar = _bar(name, len(seeds), max_steps)

        def on_step(live: int) -> None:
            bar.update(1)
            bar.set_postfix(live=live)

        try:
            out = search_episodes(planner, episodes, seeds, max_steps, on_step=on_step)
        finally:
            bar.close()
    log.debug("searched %d episodes: %d planned frames", len(seeds), planner.frames)
    return out


def _bar(name: str, episodes: int, max_steps: int):  # noqa: ANN202 (tqdm is imported lazily)
    from tqdm.auto import tqdm

    desc = f"{name} ({episodes} episodes at once)"
    return tqdm(total=max_steps, desc=desc, unit="step", dynamic_ncols=True, leave=False)


# What the forked workers play: set before the fork, inherited by the children.
_JOB: tuple | None = None


def _init_worker() -> None:
    # The caller handles Ctrl-C; one thread per worker, as many workers as cores (two
    # threads per process on two shared cores stall each other at every op).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)


def _worker(seeds: list[int], progress: bool) -> TensorDict:
    return _play(_JOB, seeds, progress)


def _forked(job: tuple, seeds: list[int], workers: int, progress: bool) -> list[TensorDict]:
    global _JOB
    _JOB = job
    share = -(-len(seeds) // workers)
    chunks = [seeds[i : i + share] for i in range(0, len(seeds), share)]
    ctx = mp.get_context("fork")
    try:
        with ProcessPoolExecutor(len(chunks), mp_context=ctx, initializer=_init_worker) as pool:
            # The first share's worker shows the progress: the shares advance together.
            shown = [progress and i == 0 for i in range(len(chunks))]
            return list(pool.map(_worker, chunks, shown))
    except BrokenProcessPool as e:
        raise RuntimeError(
            f"evaluation of {job[-1]}: a worker process died (killed, or out of memory?) "
            f"while searching episodes from seed {seeds[0]}; eval_workers=1 runs them here"
        ) from e
    finally:
        _JOB = None


def searched_result(name: str, out: TensorDict, seeds: list[int]) -> EvalResult:
    """The :class:`EvalResult` of the episodes :func:`search_episodes` played.

    Each episode's figures as :func:`~torchrl_grpo.training.evaluate` computes them from
    its own steps (the same float32 sum of the rewards).

    Args:
        name: the label in the results.
        out: :func:`search_episodes`'s output ``[episodes, max_steps]``.
        seeds: the episodes' seeds, in its order.

    Example:
        >>> from tensordict import TensorDict
        >>> out = TensorDict(mask=torch.tensor([[True, True], [True, False]]),
        ...                  reward=torch.ones(2, 2), crashed=torch.tensor([[False, False],
        ...                  [True, False]]), speed=torch.full((2, 2), 20.0), batch_size=[2, 2])
        >>> res = searched_result("search", out, [7, 8])
        >>> res.returns, res.crashed, res.lengths
        ([2.0, 1.0], [False, True], [2, 1])
    """
    result = EvalResult(name)
    lengths = out.get("mask").sum(-1).tolist()
    for i, (seed, length) in enumerate(zip(seeds, lengths, strict=True)):
        result.returns.append(float(out.get("reward")[i, :length].sum()))
        result.crashed.append(bool(out.get("crashed")[i, :length].any()))
        result.lengths.append(int(length))
        result.speeds.append(float(out.get("speed")[i, :length].float().mean()))
        result.seeds.append(seed)
    return result
