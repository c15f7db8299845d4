"""The episodes of an evaluation, in this process or on forked worker processes.

Episode ``i`` starts from ``env.set_seed(seed + i)`` wherever it runs, and its outcome is
computed by the same code in a worker as here: an evaluation on ``workers`` processes gives
the serial evaluation's numbers, episode for episode. Workers are forked (the env and the
policy, weights included, reach them as they are at the fork, nothing is pickled) and each
drives whole episodes, one at a time, on its own copy; the results come back in episode
order. A policy that draws from its own generator (the ``random`` baseline) runs on one
process: its draws run on from one episode to the next, which copies cannot reproduce.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["EpisodeOutcome", "eval_workers", "run_episodes"]

log = logging.getLogger(__name__)


@dataclass
class EpisodeOutcome:
    """What one evaluation episode gives.

    Attributes:
        seed: the episode's seed.
        ret: undiscounted return.
        crashed: whether the ego crashed.
        length: steps.
        speed: mean ego speed (m/s).
        actions: the actions played, kept for the episode replayed as a video.
    """

    seed: int
    ret: float
    crashed: bool
    length: int
    speed: float
    actions: torch.Tensor | None = None


def eval_workers(value: int | None) -> int:
    """The worker processes ``experiment.eval_workers`` asks for; ``None``: the usable cores.

    Raises:
        ValueError: a count below 1.

    Example:
        >>> eval_workers(3), eval_workers(None) >= 1
        (3, True)
    """
    if value is None:
        try:
            return max(len(os.sched_getaffinity(0)), 1)
        except AttributeError:  # no affinity on this platform (macOS)
            return os.cpu_count() or 1
    if int(value) < 1:
        raise ValueError(f"eval_workers must be >= 1, or null for the cores; got {value}")
    return int(value)


@torch.no_grad()
def play_episode(env: EnvBase, policy: Callable, seed: int, max_steps: int) -> TensorDictBase:
    """One episode from ``env.set_seed(seed)``, greedy, up to ``max_steps`` steps."""
    env.set_seed(seed)
    td = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        return env.rollout(
            max_steps, policy, auto_reset=False, tensordict=td, break_when_any_done=True
        )


def _outcome(data: TensorDictBase, seed: int, keep_actions: bool) -> EpisodeOutcome:
    reward = data.get(("next", "reward")).reshape(-1)
    return EpisodeOutcome(
        seed=seed,
        ret=float(reward.sum()),
        crashed=bool(data.get(("next", "crashed")).any()),
        length=int(reward.numel()),
        speed=float(data.get(("next", "speed")).float().mean()),
        actions=data.get("action").clone() if keep_actions else None,
    )


def run_episodes(
    env: EnvBase,
    policy: Callable,
    *,
    episodes: int,
    seed: int,
    max_steps: int,
    workers: int = 1,
    keep_first_actions: bool = False,
    progress: bool = False,
    name: str = "policy",
) -> list[EpisodeOutcome]:
    """Episodes ``seed, seed + 1, ...`` of ``policy``, on up to ``workers`` forked processes.

    Args:
        env: an unbatched env; workers drive copies, this one is not stepped then.
        policy: the policy, acting greedily.
        episodes: how many episodes.
        seed: the first episode's seed.
        max_steps: cap on an episode's length.
        workers: processes (1: here; capped by ``episodes``; without ``fork``: here).
        keep_first_actions: keep the first episode's actions (to replay it as a video).
        progress: a tqdm bar over episodes, labelled ``name``.
        name: the policy's label (the bar, error messages).

    Raises:
        RuntimeError: an episode failed in a worker (its seed, the worker's error and
            traceback), or a worker died.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> env, slower = HighwayEnv("highway-fast-v0"), ConstantActionPolicy("SLOWER")
        >>> here = run_episodes(env, slower, episodes=2, seed=0, max_steps=3)
        >>> forked = run_episodes(env, slower, episodes=2, seed=0, max_steps=3, workers=2)
        >>> [o.seed for o in forked], forked == here
        ([0, 1], True)
    """
    workers = min(int(workers), episodes)
    if workers > 1 and "fork" not in mp.get_all_start_methods():
        log.warning("no 'fork' start method here: the evaluation of %s runs in one process", name)
        workers = 1
    if workers > 1 and _draws_across_episodes(policy):
        workers = 1
    bar = _bar(progress, episodes, name)
    try:
        if workers <= 1:
            outcomes = []
            for i in range(episodes):
                outcomes.append(_episode(env, policy, seed, max_steps, keep_first_actions, i))
                if bar is not None:
                    bar.update()
            return outcomes
        return _forked(
            env, policy, episodes, seed, max_steps, workers, keep_first_actions, bar, name
        )
    finally:
        if bar is not None:
            bar.close()


def _bar(progress: bool, episodes: int, name: str):  # noqa: ANN202 (tqdm is imported lazily)
    if not progress or episodes <= 0:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=episodes, desc=name, unit="episode", dynamic_ncols=True, leave=False)


def _draws_across_episodes(policy: Callable) -> bool:
    modules = policy.modules() if isinstance(policy, torch.nn.Module) else [policy]
    return any(isinstance(v, torch.Generator) for m in modules for v in vars(m).values())


# What forked workers drive: set before the fork, inherited by the children.
_JOB: tuple[EnvBase, Callable, int, int, bool] | None = None


def _init_worker() -> None:
    # The caller handles Ctrl-C (it cancels what has not started); one thread per worker,
    # as many workers as cores.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)


def _episode(
    env: EnvBase, policy: Callable, seed: int, max_steps: int, keep_first: bool, i: int
) -> EpisodeOutcome:
    # Episode i of an evaluation, the same code here and in a worker.
    data = play_episode(env, policy, seed + i, max_steps)
    return _outcome(data, seed + i, keep_first and i == 0)


def _worker_episode(i: int) -> EpisodeOutcome:
    return _episode(*_JOB, i)


def _forked(
    env: EnvBase,
    policy: Callable,
    episodes: int,
    seed: int,
    max_steps: int,
    workers: int,
    keep_first: bool,
    bar,  # noqa: ANN001
    name: str,
) -> list[EpisodeOutcome]:
    global _JOB
    _JOB = (env, policy, seed, max_steps, keep_first)
    outcomes: list[EpisodeOutcome | None] = [None] * episodes
    pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("fork"), initializer=_init_worker)
    try:
        futures = {pool.submit(_worker_episode, i): i for i in range(episodes)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                i = futures[future]
                try:
                    outcomes[i] = future.result()
                except BrokenProcessPool as e:
                    raise RuntimeError(
                        f"evaluation of {name}: a worker process died (killed, or out of "
                        f"memory?) while driving episodes from seed {seed}; "
                        "experiment.eval_workers=1 runs them in this process"
                    ) from e
                except Exception as e:
                    # The worker's traceback is the cause (concurrent.futures keeps it).
                    raise RuntimeError(
                        f"evaluation of {name}: episode {i} (seed {seed + i}) failed in a "
                        f"worker process: {type(e).__name__}: {e}"
                    ) from e
                if bar is not None:
                    bar.update()
    finally:
        # On an error or Ctrl-C: what has not started is dropped, what runs finishes.
        pool.shutdown(wait=True, cancel_futures=True)
        _JOB = None
    return outcomes  # type: ignore[return-value]
