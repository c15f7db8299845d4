"""Select a branch and continue from its end: the multi-turn branching loop.

At a decision point, G branches run for H steps; the episode then continues from
the end of one of them, chosen by ``select``:

- ``"best"``: the branch with the highest return (the lowest index among ties);
- ``"sampled"``: a branch drawn with probabilities ``softmax(return / temperature)``;
- ``"trunk"``: branch 0, i.e. the policy's own trajectory (every branch is an
  on-policy sample, so following a fixed branch index is following the policy,
  independently of how the branches scored).

The next decision point is the chosen branch's final state, bit for bit; the loop
repeats until the episode ends.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from torchrl_grpo.branching.env_slots import EnvSlots
from torchrl_grpo.branching.keys import BRANCH_RETURN, MASK, ROOT_STEP, STATE
from torchrl_grpo.branching.rollout import RngMode, check_group_args, run_groups
from torchrl_grpo.branching.rollout_rows import BranchRun, Policy
from torchrl_grpo.branching.root_builders import as_roots
from torchrl_grpo.branching.roots import RootSource

Selection = Literal["best", "sampled", "trunk"]
SELECTED = "selected"

__all__ = [
    "SELECTED",
    "ContinuationRoots",
    "MultiTurnResult",
    "Selection",
    "multi_turn_rollout",
    "select_branches",
]


def select_branches(
    data: TensorDictBase,
    how: Selection,
    *,
    temperature: float = 1.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Choose one branch per group of a ``[R, G, T]`` rollout.

    Args:
        data: branch rollout output (reads ``branch_return``).
        how: ``"best"``, ``"sampled"`` or ``"trunk"`` (see the module docstring).
        temperature: softmax temperature of ``"sampled"`` (> 0).
        generator: random generator of ``"sampled"``.

    Returns:
        ``[R]`` int64 branch indices.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> returns = torch.tensor([[1.0, 3.0, 2.0]]).view(1, 3, 1, 1)
        >>> data = TensorDict(branch_return=returns, batch_size=[1, 3, 1])
        >>> select_branches(data, "best").tolist(), select_branches(data, "trunk").tolist()
        ([1], [0])
    """
    returns = data.get(BRANCH_RETURN)[:, :, 0].reshape(data.shape[0], data.shape[1])
    if how == "best":
        return returns.argmax(-1)
    if how == "trunk":
        return torch.zeros(returns.shape[0], dtype=torch.long)
    if how == "sampled":
        if temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {temperature}")
        probs = torch.softmax(returns.double() / temperature, -1)
        return torch.multinomial(probs, 1, generator=generator).squeeze(-1)
    raise ValueError(f"select must be 'best', 'sampled' or 'trunk', got {how!r}")


@dataclass
class MultiTurnResult:
    """Every group of a multi-turn rollout, and the path the episodes took.

    Attributes:
        groups: ``[N, G, T]`` the groups of all turns of all episodes (group ids
            unique), with a ``"selected"`` entry marking the chosen branch.
        selected: ``[N]`` the branch chosen in each group.
        episode: ``[N]`` the root (episode) each group belongs to.
        turn: ``[N]`` the turn of each group within its episode.
        final_states: ``[R]`` the state each episode stopped in (the last chosen
            branch's final state).
        ended: ``[R]`` the episode ended (``False``: stopped by ``max_turns``).

    Example:
        >>> from torchrl_grpo.branching import reset_roots
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> roots = reset_roots(env, 1, seed=0)
        >>> out = multi_turn_rollout(env, RandomPolicy(seed=0), roots, 2, 3, max_turns=2)
        >>> out.groups.batch_size, out.episode.tolist(), out.turn.tolist()
        (torch.Size([2, 2, 3]), [0, 0], [0, 1])
        >>> out.trunk(0)["step_count"].flatten().tolist()  # the chosen branches, in order
        [0, 1, 2, 3, 4, 5]
    """

    groups: TensorDict
    selected: torch.Tensor
    episode: torch.Tensor
    turn: torch.Tensor
    final_states: TensorDictBase
    ended: torch.Tensor

    def trunk(self, episode: int) -> TensorDict:
        """The steps episode ``episode`` actually took: its chosen branches, in order.

        One row per step, as a TorchRL rollout: row ``t`` holds what the policy saw
        before step ``t`` (``"observation"``, ``"ego_position"``, ...: row 0 holds the
        root's), the action, and ``("next", ...)`` what came after it. The ``T + 1``
        observations of a ``T``-step trunk are ``trunk["observation"][0]`` followed by
        ``trunk["next", "observation"]``.

        Example:
            >>> from torchrl_grpo.branching import reset_roots
            >>> from torchrl_grpo.envs import HighwayEnv
            >>> from torchrl_grpo.modules import RandomPolicy
            >>> env = HighwayEnv("merge-v0", seed=0)
            >>> roots = reset_roots(env, 1, seed=0)
            >>> trunk = multi_turn_rollout(env, RandomPolicy(seed=0), roots, 2, 2).trunk(0)
            >>> root = roots["state", "output", "observation"][0].view(torch.float32)
            >>> torch.equal(trunk["observation"][0], root)
            True
        """
        rows = (self.episode == episode).nonzero().squeeze(-1)
        rows = rows[torch.argsort(self.turn[rows])]
        steps = [self.groups[i, self.selected[i]] for i in rows.tolist()]
        return torch.cat([s[s.get(MASK)] for s in steps])


def multi_turn_rollout(
    env: EnvBase,
    policy: Policy,
    roots: TensorDictBase,
    group_size: int,
    horizon: int,
    *,
    select: Selection = "best",
    max_turns: int | None = None,
    temperature: float = 1.0,
    generator: torch.Generator | None = None,
    return_states: bool = False,
    rng: RngMode = "shared",
    seed: int = 0,
    first_group_id: int = 0,
    set_truncated: bool = True,
    exploration_type: ExplorationType = ExplorationType.RANDOM,
) -> MultiTurnResult:
    """Branch, select, continue; repeated until every episode ends.

    Each turn branches G ways (``horizon`` steps each) from the current state of
    every live episode (R at once, W branches at a time on the env), selects one
    branch per group and moves the episode to that branch's final state. An episode
    whose chosen branch ended (``done``) is over.

    Args:
        env: the env running the branches (see :func:`branch_rollout`).
        policy: the policy.
        roots: the R episodes' start roots.
        group_size: G >= 2.
        horizon: H >= 1, steps per turn.
        select: ``"best"``, ``"sampled"`` or ``"trunk"``.
        max_turns: stop after this many turns (default: at the episodes' ends).
        temperature: softmax temperature of ``"sampled"``.
        generator: random generator of ``"sampled"``.
        return_states: keep every step's states in ``groups``.
        rng: ``"shared"`` or ``"per_branch"`` (see :func:`branch_rollout`).
        seed: mixed into the per-branch seeds.
        first_group_id: group id of the first group.
        set_truncated: see :func:`branch_rollout`.
        exploration_type: how the policy acts.

    Returns:
        A :class:`MultiTurnResult`.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> from torchrl_grpo.branching import reset_roots
        >>> env = HighwayEnv("merge-v0", seed=0)
        >>> roots = reset_roots(env, 1, seed=0)
        >>> out = multi_turn_rollout(env, RandomPolicy(seed=0), roots, 2, 3, max_turns=2)
        >>> out.groups.batch_size, out.turn.tolist()
        (torch.Size([2, 2, 3]), [0, 1])
    """
    check_group_args(group_size, horizon, rng)
    if select not in ("best", "sampled", "trunk"):
        raise ValueError(f"select must be 'best', 'sampled' or 'trunk', got {select!r}")
    slots = EnvSlots(env)
    roots = as_roots(roots)
    slots.check_states(roots.get(STATE))
    n_episodes = roots.shape[0]
    live = torch.arange(n_episodes)
    cur = roots.select(STATE, ROOT_STEP)
    final = roots.get(STATE).clone()
    ended = torch.zeros(n_episodes, dtype=torch.bool)
    groups, chosen, episodes, turns = [], [], [], []
    next_id = first_group_id
    turn = 0
    while live.numel() and (max_turns is None or turn < max_turns):
        data, run = run_groups(
            slots,
            policy,
            cur,
            group_size,
            horizon,
            first_group_id=next_id,
            keep="all" if return_states else "final",
            rng=rng,
            seed=seed,
            set_truncated=set_truncated,
            exploration_type=exploration_type,
        )
        next_id += live.numel()
        choice = select_branches(data, select, temperature=temperature, generator=generator)
        step = _advance(data, run, choice, group_size)
        data.set(SELECTED, _selected_mask(data, choice))
        groups.append(data)
        chosen.append(choice)
        episodes.append(live)
        turns.append(torch.full_like(live, turn))
        final[live] = step.get(STATE)
        ended[live] = step.get("ended")
        go_on = ~step.get("ended")
        live = live[go_on]
        cur = step.select(STATE, ROOT_STEP)[go_on]
        turn += 1
    return MultiTurnResult(
        groups=torch.cat(groups),
        selected=torch.cat(chosen),
        episode=torch.cat(episodes),
        turn=torch.cat(turns),
        final_states=final,
        ended=ended,
    )


def _advance(data: TensorDict, run: BranchRun, choice: torch.Tensor, group_size: int) -> TensorDict:
    """Where each episode goes next: the chosen branch's final state, step and end flag."""
    n_roots = choice.shape[0]
    flat = torch.arange(n_roots) * group_size + choice
    root_step = data.get(ROOT_STEP)[:, 0, 0]
    return TensorDict(
        {
            STATE: run.final_states[flat],
            ROOT_STEP: root_step + run.lengths[flat],
            "ended": run.ended[flat],
        },
        batch_size=[n_roots],
    )


def _selected_mask(data: TensorDict, choice: torch.Tensor) -> torch.Tensor:
    g = torch.arange(data.shape[1]).view(1, -1, 1)
    return (g == choice.view(-1, 1, 1)).expand(data.shape).clone()


class ContinuationRoots(RootSource):
    """Groups along selected paths: each batch continues R live episodes.

    The first batch branches from R fresh resets; after every batch each episode
    moves to its selected branch's final state (the next batch's root), and an
    episode that ended is replaced by a fresh reset.

    Args:
        select: ``"best"``, ``"sampled"`` or ``"trunk"``.
        temperature: softmax temperature of ``"sampled"``.

    Example:
        >>> src = ContinuationRoots("best")
        >>> src.needs_final_states
        True
    """

    needs_final_states = True

    def __init__(self, select: Selection = "best", *, temperature: float = 1.0) -> None:
        if select not in ("best", "sampled", "trunk"):
            raise ValueError(f"select must be 'best', 'sampled' or 'trunk', got {select!r}")
        self.select = select
        self.temperature = temperature
        self._live: TensorDict | None = None
        self.episodes_finished = 0

    def next_roots(self, env: EnvBase, policy: Policy, num_roots: int) -> TensorDict:
        """The live episodes' current states, topped up with fresh resets."""
        live = self._live
        n_live = 0 if live is None else live.shape[0]
        if n_live < num_roots:
            fresh = self.fresh_roots(env, num_roots - n_live)
            live = fresh if live is None or n_live == 0 else torch.cat([live, fresh])
        self._live = live[:num_roots]
        return self._live

    def observe(
        self,
        data: TensorDictBase,
        final_states: TensorDictBase | None,
        ended: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> None:
        """Move every episode to its selected branch's end; drop those that ended."""
        if final_states is None:
            raise ValueError("ContinuationRoots needs the branches' final states")
        choice = select_branches(
            data, self.select, temperature=self.temperature, generator=generator
        )
        data.set(SELECTED, _selected_mask(data, choice))
        rows = torch.arange(choice.shape[0])
        lengths = data.get(MASK).sum(-1)[rows, choice]
        done = ended[rows, choice]
        nxt = TensorDict(
            {
                STATE: final_states[rows, choice],
                ROOT_STEP: data.get(ROOT_STEP)[:, 0, 0] + lengths,
            },
            batch_size=[choice.shape[0]],
        )
        self.episodes_finished += int(done.sum())
        self._live = nxt[~done]

    def state_dict(self) -> dict[str, Any]:
        """The seed chain, ``episodes_finished`` and the ``"live"`` episodes' roots."""
        return {
            **super().state_dict(),
            "episodes_finished": self.episodes_finished,
            "live": self._live,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (see :meth:`RootSource.load_state_dict`)."""
        super().load_state_dict(state_dict)
        if "episodes_finished" in state_dict:
            self.episodes_finished = int(state_dict["episodes_finished"])
        if "live" in state_dict:
            self._live = state_dict["live"]
