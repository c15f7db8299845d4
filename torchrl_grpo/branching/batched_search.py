"""Test-time search at batch speed: all of an evaluation's episodes planned at once.

:class:`~torchrl_grpo.branching.LookaheadPolicy` plans one state at a time: each
decision is one rollout of ``n_actions`` rows. :func:`search_episodes` plays N episodes
in lock-step instead; at every step the N live episodes' states are repeated once per
action into the N x A rows of ONE rollout of the planner's batched simulator, scored by
the planner's own :meth:`~torchrl_grpo.branching.LookaheadPolicy.returns`, and each
episode plays :func:`~torchrl_grpo.branching.lookahead.best_actions`' choice: the same
scores and the same tie-breaking as the one-state planner, so the same episodes. An
episode that ends drops out of the planning; its env rows are stepped on and ignored.

The episodes are either the N worlds of one batched simulator
(:class:`~torchrl_grpo.envs.TensorHighwayEnv`, every tensor of an episode's step in one
call) or N snapshot envs (:class:`~torchrl_grpo.envs.HighwayEnv`) stepped in lock-step,
whose N states reach the planner in one batch (its ``import_state`` converts them in one
bridge call).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from torchrl_grpo.branching.env_slots import has_batched_worlds
from torchrl_grpo.branching.keys import STATE
from torchrl_grpo.branching.lookahead import LookaheadPolicy, best_actions
from torchrl_grpo.sim.rng import seed_keys

__all__ = ["search_episodes", "seeded_worlds"]

# What each step keeps of an episode (the evaluation's outcome is computed from them).
_KEPT = ("reward", "crashed", "speed")


def seeded_worlds(env: EnvBase, seeds: Sequence[int]) -> TensorDictBase:
    """Reset world ``i`` of a batched simulator to the episode that ``seeds[i]`` starts.

    The episode a one-world env starts after ``env.set_seed(seeds[i])`` and
    ``env.reset()`` (how :func:`~torchrl_grpo.training.evaluate` seeds episode ``i``): a
    world's draws depend on its own stream only, never on the other rows.

    Args:
        env: a :class:`~torchrl_grpo.envs.TensorHighwayEnv` of ``len(seeds)`` worlds.
        seeds: one seed per world.

    Returns:
        The reset's output ``[len(seeds)]``.

    Example:
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> one = TensorHighwayEnv(num_envs=1)
        >>> _ = one.set_seed(7)
        >>> first = one.reset()
        >>> many = seeded_worlds(TensorHighwayEnv(num_envs=2), [3, 7])
        >>> torch.equal(many["observation"][1], first["observation"][0])
        True
    """
    n = env.batch_size[0] if env.batch_dims == 1 else 0
    if not has_batched_worlds(env) or n != len(seeds):
        raise ValueError(
            f"seeded_worlds needs a batched simulator of {len(seeds)} worlds (one per seed); "
            f"got {type(env).__name__} of batch {tuple(env.batch_size)}"
        )
    one = torch.zeros(1, dtype=torch.int64, device=env.device)
    keys = torch.cat([seed_keys(one, int(s)) for s in seeds])
    state = env.get_state()
    state.set(("rng", "key"), keys)
    state.set(("rng", "counter"), torch.zeros_like(keys))
    env.reset(TensorDict({STATE: state}, batch_size=env.batch_size), set_state=True)
    return env.reset()


@torch.no_grad()
def search_episodes(
    planner: LookaheadPolicy,
    episodes: EnvBase | Sequence[EnvBase],
    seeds: Sequence[int],
    max_steps: int,
) -> TensorDict:
    """Play one episode per seed with ``planner``'s actions, all episodes in lock-step.

    Episode ``i`` starts as :func:`~torchrl_grpo.training.evaluate` starts it from
    ``seeds[i]``, and plays what ``planner`` would play from each of its states: the
    per-decision planner's actions and returns, episode for episode, with one planning
    rollout of ``N x n_actions`` rows per step instead of ``N`` rollouts of
    ``n_actions``. The planner's env should hold ``n_actions`` rows per episode (more
    episodes run in waves of its rows).

    Args:
        planner: the lookahead planner; its env must be a batched simulator.
        episodes: where the episodes run: a batched simulator of ``len(seeds)`` worlds
            (:class:`~torchrl_grpo.envs.TensorHighwayEnv`), or ``len(seeds)`` snapshot
            envs (:class:`~torchrl_grpo.envs.HighwayEnv`), all built with
            ``return_state=True``.
        seeds: the episodes' seeds.
        max_steps: cap on an episode's length.

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
    return out


class _Worlds:
    """N episodes as the N worlds of one batched simulator."""

    def __init__(self, env: EnvBase, seeds: Sequence[int]) -> None:
        _check_returns_state(env)
        self.env = env
        self.td = seeded_worlds(env, seeds)

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
