"""Test-time search at batch speed: all of an evaluation's episodes planned at once.

:class:`~torchrl_grpo.branching.LookaheadPolicy` plans one state at a time: each
decision is one rollout of ``n_actions`` rows. :func:`search_episodes` plays N episodes
in lock-step instead; at every step the N live episodes' states are repeated once per
action into the N x A rows of ONE rollout of the planner's batched simulator, scored by
the planner's own :meth:`~torchrl_grpo.branching.LookaheadPolicy.returns`, and each
episode plays :func:`~torchrl_grpo.branching.lookahead.best_actions`' choice: the same
scores and the same tie-breaking as the one-state planner, so the same episodes. An
episode that ends drops out of the planning; its env rows are stepped on and ignored.

The episodes are either the N worlds of one tensor simulator
(:class:`~torchrl_grpo.envs.TensorHighwayEnv`, started from highway-env's episode
starts: :func:`highway_starts`) or N snapshot envs (:class:`~torchrl_grpo.envs.HighwayEnv`)
stepped in lock-step, whose N states reach the planner in one batch (its
``import_state`` converts them in one bridge call).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from torchrl_grpo.branching.env_slots import has_batched_worlds
from torchrl_grpo.branching.keys import STATE
from torchrl_grpo.branching.lookahead import LookaheadPolicy, best_actions
from torchrl_grpo.envs.highway.wrapper import HighwayEnv

__all__ = ["highway_starts", "search_episodes"]

# What each step keeps of an episode (the evaluation's outcome is computed from them).
_KEPT = ("reward", "crashed", "speed")


def highway_starts(env: EnvBase, seeds: Sequence[int]) -> TensorDictBase:
    """Restore world ``i`` of a tensor simulator to highway-env's episode start of ``seeds[i]``.

    The evaluation's episodes on the tensor simulator: episode ``i`` starts where
    highway-env's episode from ``env.set_seed(seeds[i])`` starts, imported through the
    bridge (as :func:`~torchrl_grpo.training.transfer.evaluate_on_tensor` starts them),
    so that its figures pair with highway-env's.

    Args:
        env: a :class:`~torchrl_grpo.envs.TensorHighwayEnv` of ``len(seeds)`` worlds.
        seeds: one highway-env seed per world.

    Returns:
        The restore's output ``[len(seeds)]``.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv
        >>> highway = HighwayEnv("highway-fast-v0")
        >>> _ = highway.set_seed(7)
        >>> first = highway.reset()
        >>> many = highway_starts(TensorHighwayEnv(num_envs=2), [3, 7])
        >>> torch.allclose(many["observation"][1], first["observation"], atol=1e-6)
        True
    """
    n = env.batch_size[0] if env.batch_dims == 1 else 0
    if not hasattr(env, "state_from_highway") or n != len(seeds):
        raise ValueError(
            f"highway_starts needs a tensor simulator of {len(seeds)} worlds (one per seed); "
            f"got {type(env).__name__} of batch {tuple(env.batch_size)}"
        )
    highway = HighwayEnv(env.scenario, env.overrides)
    states = []
    for seed in seeds:
        highway.set_seed(int(seed))
        highway.reset()
        states.append(highway.get_state())
    start = env.state_from_highway(torch.stack(states))
    return env.reset(TensorDict({STATE: start}, batch_size=[n]), set_state=True)


@torch.no_grad()
def search_episodes(
    planner: LookaheadPolicy,
    episodes: EnvBase | Sequence[EnvBase],
    seeds: Sequence[int],
    max_steps: int,
    on_step: Callable[[int], None] | None = None,
) -> TensorDict:
    """Play one episode per seed with ``planner``'s actions, all episodes in lock-step.

    Episode ``i`` starts where highway-env's episode from ``seeds[i]`` starts (on the
    tensor simulator: imported, :func:`highway_starts`), and plays what ``planner``
    plays from each of its states: the per-decision planner's actions and returns,
    episode for episode, with one planning
    rollout of ``N x n_actions`` rows per step instead of ``N`` rollouts of
    ``n_actions``. The planner's env should hold ``n_actions`` rows per episode (more
    episodes run in waves of its rows).

    Args:
        planner: the lookahead planner; its env must be a batched simulator.
        episodes: where the episodes run: a tensor simulator of ``len(seeds)`` worlds
            (:class:`~torchrl_grpo.envs.TensorHighwayEnv`), or ``len(seeds)`` snapshot
            envs (:class:`~torchrl_grpo.envs.HighwayEnv`), all built with
            ``return_state=True``.
        seeds: the episodes' seeds.
        max_steps: cap on an episode's length.
        on_step: called after every step with the number of episodes still running
            (for progress).

    Returns:
        ``[N, max_steps]``: ``"action"`` (-1 after an episode's end), ``"reward"``,
        ``"crashed"``, ``"speed"`` and ``"mask"`` (the step was played; zeros after).

    Raises:
        ValueError: a planner that does not plan on a batched simulator, or episodes
            that do not match the seeds.

    Example:
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> from torchrl_grpo.modules import make_scripted_policy
        >>> plan = TensorHighwayEnv(num_envs=2 * 5)
        >>> planner = LookaheadPolicy(plan, make_scripted_policy("slower"), horizon=2)
        >>> out = search_episodes(planner, TensorHighwayEnv(num_envs=2, return_state=True),
        ...                       seeds=[0, 1], max_steps=3)
        >>> out.batch_size, out["mask"].sum(-1).tolist()
        (torch.Size([2, 3]), [3, 3])
    """
    if not has_batched_worlds(planner.env):
        raise ValueError(
            "search_episodes plans all episodes as rows of one rollout: the planner's env must "
            f"be a batched simulator (TensorHighwayEnv), got {type(planner.env).__name__}"
        )
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    lanes = _Worlds(episodes, seeds) if isinstance(episodes, EnvBase) else _Lanes(episodes, seeds)
    n = len(seeds)
    out = TensorDict(
        action=torch.full((n, max_steps), -1, dtype=torch.int64),
        mask=torch.zeros(n, max_steps, dtype=torch.bool),
        batch_size=[n, max_steps],
    )
    live = torch.ones(n, dtype=torch.bool)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for t in range(max_steps):
            rows = live.nonzero().squeeze(-1)
            if rows.numel() == 0:
                break
            # The live episodes' branches, rows of one rollout; the one-state rule picks.
            actions = best_actions(planner.returns(lanes.observe(rows))).cpu()
            step = lanes.step(rows, actions)
            for key in _KEPT:
                if key not in out.keys():
                    out.set(key, torch.zeros(n, max_steps, dtype=step.get(key).dtype))
                out.get(key)[rows, t] = step.get(key).reshape(-1).cpu()
            out.get("action")[rows, t] = actions
            out.get("mask")[rows, t] = True
            live[rows] = ~step.get("done").reshape(-1).cpu()
            if on_step is not None:
                on_step(int(live.sum()))
    return out


class _Worlds:
    """N episodes as the N worlds of one batched simulator."""

    def __init__(self, env: EnvBase, seeds: Sequence[int]) -> None:
        _check_returns_state(env)
        self.env = env
        self.td = highway_starts(env, seeds)

    def observe(self, rows: torch.Tensor) -> TensorDictBase:
        return self.td[rows.to(self.env.device)]

    def step(self, rows: torch.Tensor, actions: torch.Tensor) -> TensorDictBase:
        # Every world steps (one batched call); the ended ones' steps are ignored.
        device = self.env.device
        full = torch.zeros(self.env.batch_size, dtype=torch.int64, device=device)
        full[rows.to(device)] = actions.to(device)
        stepped = self.env.step(self.td.set("action", full))
        self.td = step_mdp(stepped)
        return stepped.get("next").select(*_KEPT, "done")[rows.to(device)]


class _Lanes:
    """N episodes on N snapshot envs, stepped in lock-step."""

    def __init__(self, envs: Sequence[EnvBase], seeds: Sequence[int]) -> None:
        if len(envs) != len(seeds):
            raise ValueError(f"{len(seeds)} seeds need as many envs, got {len(envs)}")
        for env in envs:
            _check_returns_state(env)
        self.envs = list(envs)
        self.tds = []
        for env, seed in zip(self.envs, seeds, strict=True):
            env.set_seed(int(seed))
            self.tds.append(env.reset())

    def observe(self, rows: torch.Tensor) -> TensorDictBase:
        # One batch: the planner imports its N states in one call.
        return torch.stack([self.tds[i] for i in rows.tolist()])

    def step(self, rows: torch.Tensor, actions: torch.Tensor) -> TensorDictBase:
        outs = []
        for i, action in zip(rows.tolist(), actions, strict=True):
            stepped = self.envs[i].step(self.tds[i].set("action", action.clone()))
            self.tds[i] = step_mdp(stepped)
            outs.append(stepped.get("next").select(*_KEPT, "done"))
        return torch.stack(outs)


def _check_returns_state(env: EnvBase) -> None:
    if not getattr(env, "return_state", False):
        raise ValueError(
            f"search_episodes plans from every step's state: build the {type(env).__name__} "
            "it plays with return_state=True"
        )
