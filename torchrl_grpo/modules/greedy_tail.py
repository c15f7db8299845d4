"""A rollout policy that samples the first steps of each branch and acts greedily after."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type

__all__ = ["EXPLORED", "GreedyTail"]

EXPLORED = "explored"
"""bool: ``True`` on steps where :class:`GreedyTail` sampled the action."""

_ROOT_STEP = "root_step"
_STEP_COUNT = "step_count"


class GreedyTail(TensorDictModuleBase):
    """Sample the first ``explore_steps`` actions of a branch, then act greedily.

    A branch's return scores everything the branch did. When every step samples, the
    return of a group member mixes the effect of its first actions with the noise of
    all its later samples, and it scores the sampling policy while evaluation runs the
    greedy one. With a greedy tail, a branch's return is the value of its first
    ``explore_steps`` sampled actions *followed by the greedy policy*: on a
    deterministic simulator, branches that sample the same first actions get the same
    return, and the group compares exactly the choices the loss trains. This is the
    rollout scheme of approximate policy iteration (Monte Carlo rollouts of the current
    greedy policy after a sampled action).

    The branch-local step is ``step_count - root_step`` (both written by the branch
    rollouts). Steps at or after ``explore_steps`` get the greedy action and
    ``"explored" = False``; train on ``mask & explored`` only, since their actions were
    not drawn from the policy's distribution. Under
    ``set_exploration_type(DETERMINISTIC)`` (evaluation, greedy trunks) every step is
    greedy.

    Args:
        policy: a probabilistic actor (reads its ``in_keys``, writes ``action`` and,
            when it returns one, ``action_log_prob``).
        explore_steps: how many steps at the start of each branch sample (>= 1).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Categorical
        >>> from torchrl_grpo.modules import make_discrete_actor
        >>> actor = make_discrete_actor(torch.nn.Linear(4, 3), Categorical(3))
        >>> rollout_policy = GreedyTail(actor, explore_steps=1)
        >>> td = TensorDict(observation=torch.randn(2, 4), root_step=torch.tensor([5, 5]),
        ...                 step_count=torch.tensor([[5], [6]]), batch_size=[2])
        >>> rollout_policy(td)["explored"].tolist()
        [True, False]
    """

    def __init__(self, policy: TensorDictModuleBase, explore_steps: int) -> None:
        super().__init__()
        if isinstance(explore_steps, bool) or not isinstance(explore_steps, int):
            raise TypeError(f"explore_steps must be an int, got {explore_steps!r}")
        if explore_steps < 1:
            raise ValueError(f"explore_steps must be >= 1, got {explore_steps}")
        self.policy = policy
        self.explore_steps = explore_steps
        self.in_keys = [*policy.in_keys, _ROOT_STEP, _STEP_COUNT]
        self.out_keys = [*policy.out_keys, EXPLORED]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the action (sampled or greedy per row) and ``"explored"``."""
        mode = exploration_type()
        if mode in (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN):
            out = self.policy(tensordict)
            explored = torch.zeros(out.batch_size, dtype=torch.bool, device=out.device)
            return out.set(EXPLORED, explored)
        for key in (_ROOT_STEP, _STEP_COUNT):
            if key not in tensordict.keys():
                raise KeyError(
                    f"GreedyTail needs {key!r} to know each row's step within its branch; "
                    "run it through torchrl_grpo.branching (branch_rollout, GroupCollector)"
                )
        t = tensordict.get(_STEP_COUNT).reshape(tensordict.batch_size) - tensordict.get(
            _ROOT_STEP
        ).reshape(tensordict.batch_size)
        explored = t < self.explore_steps
        sampled = self.policy(tensordict.clone(False))
        if bool(explored.all()):
            return tensordict.update(sampled).set(EXPLORED, explored)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            greedy = self.policy(tensordict.clone(False))
        out_keys = [k for k in self.policy.out_keys if k in sampled.keys(True)]
        for key in out_keys:
            a, b = sampled.get(key), greedy.get(key)
            rows = explored.reshape(explored.shape + (1,) * (a.ndim - explored.ndim))
            tensordict.set(key, torch.where(rows, a, b))
        return tensordict.set(EXPLORED, explored)
