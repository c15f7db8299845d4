"""Deterministic evaluation on fixed seeds, the scripted baselines, and a checkpoint's report.

Episode ``i`` of an evaluation starts from ``env.set_seed(eval_seed + i)``: every
policy, every evaluation of a run and every run with the same ``eval_seed`` drive
the same traffic. The trained policy acts greedily (the mode of its categorical,
:class:`~torchrl_grpo.modules.DeterministicActor`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.modules.scripted.actions import LONGITUDINAL_ACTIONS, ConstantActionPolicy
from torchrl_grpo.modules.scripted.policy_registry import SCRIPTED_POLICIES, make_scripted_policy
from torchrl_grpo.training.baseline_cache import cache_key, read_cached
from torchrl_grpo.training.checkpoint import load_checkpoint
from torchrl_grpo.training.config import typed_config
from torchrl_grpo.training.env_builder import make_env, make_layout, tensor_covers
from torchrl_grpo.training.eval_episodes import eval_workers, run_episodes
from torchrl_grpo.training.model_builder import make_policy
from torchrl_grpo.training.pretrained import load_run_policy
from torchrl_grpo.training.results import EvalResult, format_table, paired_verdicts
from torchrl_grpo.training.run_plots import plot_comparison, plot_run_curve, save_gif
from torchrl_grpo.training.search_eval import evaluate_search, is_stochastic, search_policy

__all__ = [
    "BASELINE_LABELS",
    "EvalReport",
    "EvalResult",
    "baseline_policy",
    "evaluate",
    "evaluate_checkpoint",
    "format_table",
    "plot_comparison",
    "save_gif",
]

log = logging.getLogger(__name__)

#: Display names of the scripted baselines (keys of ``SCRIPTED_POLICIES``).
BASELINE_LABELS = {
    "random": "random",
    "idle": "always-IDLE",
    "slower": "always-SLOWER",
    "rule": "rule policy",
}


def baseline_policy(
    name: str, layout: KinematicsLayout | None, n_actions: int, seed: int = 0
) -> TensorDictModuleBase | None:
    """A scripted baseline by name, or ``None`` where it does not apply.

    The scripted policies speak highway-env's 5-action DiscreteMetaAction on a
    Kinematics observation; on a longitudinal-only one (3 actions, intersection-v0)
    ``idle``, ``slower`` and ``faster`` apply as constant actions; for other action sets
    or observations only ``random`` applies.

    Example:
        >>> baseline_policy("slower", None, 5) is not None, baseline_policy("rule", None, 3)
        (True, None)
        >>> from tensordict import TensorDict
        >>> slower = baseline_policy("slower", None, 3)  # intersection-v0's SLOWER is 0
        >>> slower(TensorDict(observation=torch.zeros(2, 15, 7), batch_size=[2]))["action"].tolist()
        [0, 0]
    """
    if name == "random":
        return make_scripted_policy("random", n_actions=n_actions, seed=seed)
    if n_actions == len(LONGITUDINAL_ACTIONS) and name in LONGITUDINAL_ACTIONS:
        return ConstantActionPolicy(LONGITUDINAL_ACTIONS[name])
    if n_actions != 5 or (name == "rule" and layout is None):
        return None
    return make_scripted_policy(name, layout)


def evaluate(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    *,
    episodes: int,
    seed: int,
    max_steps: int = 1000,
    name: str = "policy",
    deterministic: bool = True,
    record: EnvBase | None = None,
    workers: int = 1,
    progress: bool = False,
) -> tuple[EvalResult, torch.Tensor | None]:
    """Run ``episodes`` episodes from seeds ``seed, seed + 1, ...``.

    Args:
        env: an unbatched env (a :class:`~torchrl_grpo.envs.HighwayEnv`).
        policy: the policy; learned actors are wrapped in ``DeterministicActor``
            when ``deterministic``.
        episodes: how many episodes.
        seed: seed of the first episode.
        max_steps: cap on an episode's length.
        name: the label in the results.
        deterministic: act greedily.
        record: an env built with ``render_mode="rgb_array"``: the first episode is
            replayed there (same seed, same actions) and returned as a video.
        workers: processes driving the episodes (forked; the same results as one,
            episode for episode: :func:`~torchrl_grpo.training.eval_episodes.run_episodes`).
        progress: a tqdm bar over the episodes.

    Returns:
        The results and, with ``record``, a ``(1, T, 3, H, W)`` uint8 video.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> res, _ = evaluate(HighwayEnv("highway-fast-v0"), ConstantActionPolicy("SLOWER"),
        ...                   episodes=1, seed=0, max_steps=3)
        >>> res.lengths
        [3]
    """
    if deterministic and isinstance(policy, TensorDictModuleBase) and is_stochastic(policy):
        policy = DeterministicActor(policy)
    outcomes = run_episodes(
        env,
        policy,
        episodes=episodes,
        seed=seed,
        max_steps=max_steps,
        workers=workers,
        keep_first_actions=record is not None,
        progress=progress,
        name=name,
    )
    result = EvalResult(name)
    for out in outcomes:
        result.returns.append(out.ret)
        result.crashed.append(out.crashed)
        result.lengths.append(out.length)
        result.speeds.append(out.speed)
        result.seeds.append(out.seed)
    video = None
    if record is not None and outcomes:
        video = _replay_video(record, outcomes[0].actions, outcomes[0].seed)
    return result, video


@torch.no_grad()
def _replay_video(env: EnvBase, actions: torch.Tensor, seed: int) -> torch.Tensor:
    # Replaying the recorded actions from the same seed keeps rendering out of the
    # timed evaluation and gives the same episode bit for bit.
    env.set_seed(seed)
    env.reset()
    frames = [env.render()]
    for action in actions:
        step = env.step(TensorDict(action=action.clone()))
        frames.append(env.render())
        if bool(step.get(("next", "done"))):
            break
    video = torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2).contiguous()
    return video.unsqueeze(0)


@dataclass
class EvalReport:
    """What :func:`evaluate_checkpoint` wrote.

    Attributes:
        results: one :class:`EvalResult` per policy (the trained one first).
        table: the Markdown table (``results.md``).
        out_dir: the output folder.
        files: written files by kind (``table``, ``json``, ``bars``, ``curve``, ``video``).
    """

    results: list[EvalResult]
    table: str
    out_dir: Path
    files: dict[str, Path] = field(default_factory=dict)


def _curve(
    run_cfg: DictConfig, history: list[dict], results: list[EvalResult], frames: int, out: Path
) -> Path:
    # This evaluation is the final point (its seeds); the periodic rows and the baselines
    # the run cached on their seeds draw the curve (nothing more is evaluated for it).
    exp = run_cfg.experiment
    periodic = [r for r in history if r.get("seed", exp.eval_seed) == exp.eval_seed]
    cache = exp.get("baseline_cache")
    baselines = []
    if periodic and cache is not None:
        for name in exp.baselines:
            key = cache_key(
                run_cfg.env, name, int(exp.eval_seed), int(exp.eval_episodes), int(run_cfg.seed)
            )
            cached = read_cached(Path(str(cache)) / key)
            if cached is not None:
                baselines.append(cached)
    return plot_run_curve(
        periodic,
        out / "learning_curve.png",
        label=str(run_cfg.algo.name),
        baselines=baselines,
        final=results,
        final_frames=frames,
        title=f"{run_cfg.env.scenario}: deterministic evaluation",
    )


def _baseline(
    name: str, env_cfg: DictConfig, env: EnvBase
) -> tuple[str, TensorDictModuleBase | None]:
    # A baseline is a scripted policy by name or another run's checkpoint (a path to a
    # .pt file: its policy, greedy, on the same episodes; paired like the scripted ones).
    if name.endswith(".pt"):
        saved = load_checkpoint(name)
        policy = load_run_policy(name, env_cfg, env, role=f"baselines entry {name}")
        run = Path(name).resolve().parent.name
        return f"{saved['config']['algo']['name']} ({saved['frames']} frames, {run})", policy
    if name not in SCRIPTED_POLICIES:
        raise ValueError(
            f"baselines entry {name!r} is neither a scripted policy "
            f"({', '.join(SCRIPTED_POLICIES)}) nor a checkpoint path ending in .pt"
        )
    layout = make_layout(env)
    policy = baseline_policy(name, layout, int(env.action_spec.n), seed=0)
    return BASELINE_LABELS.get(name, name), policy


def evaluate_checkpoint(cfg: DictConfig, out_dir: str | Path) -> EvalReport:
    """``scripts/evaluate.py``: the trained policy of ``cfg.checkpoint`` and the baselines.

    Args:
        cfg: the ``conf/evaluate.yaml`` config. With ``checkpoint`` set, the env and
            the network come from the checkpoint's own config; without, only the
            baselines run on ``cfg.env``. With ``search_horizon=H > 0``, the lookahead
            planner over the trained policy (:func:`search_policy`) is evaluated too,
            in the row after it; where the tensor simulator covers the env, all its
            episodes at once (:func:`~torchrl_grpo.training.search_eval.evaluate_search`:
            the same episodes). Episodes run on ``eval_workers`` forked processes
            (``None``: the cores), each policy with a progress bar.
        out_dir: where the table, JSON, plots and video go.

    Raises:
        ValueError: a negative ``search_horizon``, or one without a checkpoint; a
            ``baselines`` entry that is neither a scripted policy's name nor the path
            of a checkpoint (``.pt``) of a run on the same env (another run's policy,
            evaluated greedily on the same episodes and paired like the scripted ones).

    Example:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"env": {"scenario": "highway-fast-v0", "config": {},
        ...     "max_episode_steps": 2}, "checkpoint": None, "episodes": 1, "seed": 0,
        ...     "baselines": ["slower"], "video": False})
        >>> evaluate_checkpoint(cfg, tempfile.mkdtemp()).results[0].name
        'always-SLOWER'
    """
    horizon = int(cfg.get("search_horizon") or 0)
    if horizon < 0:
        raise ValueError(f"search_horizon must be >= 0 (0: no search), got {horizon}")
    if horizon and not cfg.checkpoint:
        raise ValueError(
            f"search_horizon={horizon} searches over a trained policy: give checkpoint=..."
        )
    out_dir = Path(out_dir)
    env_cfg = cfg.env
    seed = cfg.seed
    history: list[dict] = []
    run_cfg = None
    ckpt = None
    if cfg.checkpoint:
        ckpt = load_checkpoint(cfg.checkpoint)
        # Typed by today's schemas: older spellings (roots=continuation) read as today's.
        run_cfg = typed_config(ckpt["config"])
        env_cfg = run_cfg.env
        history = list(ckpt.get("eval_history") or [])
        if seed is None:
            seed = int(run_cfg.experiment.final_eval_seed)
    seed = 10_000 if seed is None else int(seed)
    env = make_env(env_cfg, seed=seed)
    # Every baseline is resolved before any episode runs: a misspelt name, a wrong path
    # or a run of another env fails at once and costs nothing.
    baselines = [_baseline(str(name), env_cfg, env) for name in cfg.baselines]
    # Only once the checkpoints loaded: a wrong path leaves no empty folder behind.
    out_dir.mkdir(parents=True, exist_ok=True)
    max_steps = int(env_cfg.get("max_episode_steps", 1000))
    results: list[EvalResult] = []
    files: dict[str, Path] = {}
    episodes = int(cfg.episodes)
    # Forked workers: the same table as one process, episode for episode, sooner.
    par = {"workers": eval_workers(cfg.get("eval_workers")), "progress": True}
    if ckpt is not None:
        policy = make_policy(run_cfg.model, env)
        policy.load_state_dict(ckpt["policy"])
        record = make_env(env_cfg, render_mode="rgb_array") if cfg.video else None
        res, video = evaluate(
            env,
            policy,
            episodes=episodes,
            seed=seed,
            max_steps=max_steps,
            **par,
            name=f"{run_cfg.algo.name} ({ckpt['frames']} frames)",
            record=record,
        )
        results.append(res)
        if video is not None:
            files["video"] = save_gif(video, out_dir / "eval_episode.gif")
        if horizon > 0:
            label = f"lookahead H={horizon} over the policy"
            if tensor_covers(env_cfg):
                # All episodes in lock-step, one planning rollout per step: the same
                # episodes as the planner deciding one state at a time.
                res = evaluate_search(
                    env_cfg,
                    policy,
                    horizon,
                    episodes=episodes,
                    seed=seed,
                    max_steps=max_steps,
                    name=label,
                    **par,
                )
            else:
                res, _ = evaluate(
                    make_env(env_cfg, seed=seed, return_state=True),
                    search_policy(env_cfg, policy, horizon),
                    episodes=episodes,
                    seed=seed,
                    max_steps=max_steps,
                    **par,
                    name=label,
                )
            results.append(res)
    for label, policy in baselines:
        if policy is None:
            log.warning("baseline %r does not apply to %s: skipped", label, env_cfg.scenario)
            continue
        res, _ = evaluate(
            env, policy, episodes=episodes, seed=seed, max_steps=max_steps, **par, name=label
        )
        results.append(res)
    table = format_table(results)
    header = (
        f"{env_cfg.scenario}, {episodes} deterministic episodes, "
        f"seeds {seed}..{seed + episodes - 1}"
    )
    verdicts = ""
    if ckpt is not None and len(results) > 1:
        # "Beats" is paired on these episodes (the training issue's definition).
        verdicts = f"\n{paired_verdicts(results[0], results[1:])}\n"
        if horizon > 0 and len(results) > 2:
            # The search against each baseline too (results[1] is the search).
            verdicts += f"{paired_verdicts(results[1], results[2:])}\n"
    files["table"] = out_dir / "results.md"
    files["table"].write_text(f"{header}\n\n{table}\n{verdicts}")
    files["json"] = out_dir / "results.json"
    files["json"].write_text(json.dumps([r.to_dict() for r in results], indent=1))
    if results:
        files["bars"] = plot_comparison(results, out_dir / "comparison.png", title=header)
    if history:
        files["curve"] = _curve(run_cfg, history, results, int(ckpt["frames"]), out_dir)
    return EvalReport(results=results, table=table, out_dir=out_dir, files=files)
