"""A rollout policy that samples the first steps of each branch and acts greedily after."""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type

from torchrl_grpo.modules.forward_sharing import shared_forward

__all__ = ["EXPLORED", "FirstAction", "GreedyTail"]

FirstAction = Literal["sample", "enumerate"]

EXPLORED = "explored"
"""bool: ``True`` on steps where :class:`GreedyTail` sampled the action."""

_BRANCH = "branch"
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

    With ``first_action="enumerate"`` (discrete actions), a branch's first action is not
    sampled but set by its index in the group: branch ``b`` takes action ``b mod n``.
    A group of ``G = n`` branches then compares every action from its root, each
    followed by the greedy policy: the group's returns are the ``H``-step values
    ``Q(s, a)`` of all actions, and the group-normalised advantage ranks them. Sampled
    first actions stop exploring once the policy is nearly deterministic (every branch
    draws the same action and the group's returns are all equal); enumerated ones
    never do. The written ``action_log_prob`` is the current policy's log-probability
    of the enumerated action, so the clipped ratio of the loss starts at 1.

    Args:
        policy: a probabilistic actor (reads its ``in_keys``, writes ``action`` and,
            when it returns one, ``action_log_prob``).
        explore_steps: how many steps at the start of each branch sample (>= 1).
        first_action: ``"sample"`` the first action from the policy, or
            ``"enumerate"`` it from the branch index (needs ``"branch"`` in the input
            and a categorical actor; later explored steps still sample).
        tail_policy: the actor whose greedy actions the tail (and deterministic mode)
            takes; ``None``: ``policy`` itself. A copy of the policy refreshed only now
            and then keeps the evaluated policy fixed over several updates, as
            approximate policy iteration evaluates one policy before improving it. A
            fixed base policy (a scripted one, which writes only the action) makes the
            group's returns ``Q_base(s, a)``: a target that does not move with the
            learner, the one-step improvement of rollout algorithms.
        learner_steps: with a ``tail_policy``, the greedy steps ``policy`` itself takes
            after the explored ones, before ``tail_policy`` takes over. The group then
            scores each action followed by what the learner does next, so an action
            that is safe only because the base policy would react on the next step
            (and the learner would not) scores as what it is for the learner.
        learner_branches: with ``learner_steps``, only the branches below this index
            take them; the others follow ``tail_policy`` right after their explored
            steps (``None``: every branch). With ``first_action="enumerate"`` and
            ``2 n`` branches, a group then scores every action twice: followed by the
            learner, and followed by the base policy alone.

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
        >>> every_action = GreedyTail(actor, explore_steps=1, first_action="enumerate")
        >>> zeros = torch.zeros(4, dtype=torch.long)
        >>> td = TensorDict(observation=torch.randn(4, 4), root_step=zeros,
        ...                 step_count=zeros.unsqueeze(-1),
        ...                 branch=torch.arange(4), batch_size=[4])
        >>> every_action(td)["action"].tolist()
        [0, 1, 2, 0]
    """

    def __init__(
        self,
        policy: TensorDictModuleBase,
        explore_steps: int,
        first_action: FirstAction = "sample",
        tail_policy: TensorDictModuleBase | None = None,
        learner_steps: int = 0,
        learner_branches: int | None = None,
    ) -> None:
        super().__init__()
        if isinstance(explore_steps, bool) or not isinstance(explore_steps, int):
            raise TypeError(f"explore_steps must be an int, got {explore_steps!r}")
        if explore_steps < 1:
            raise ValueError(f"explore_steps must be >= 1, got {explore_steps}")
        if first_action not in ("sample", "enumerate"):
            raise ValueError(f"first_action must be 'sample' or 'enumerate', got {first_action!r}")
        if first_action == "enumerate" and not hasattr(policy, "dist_sample_keys"):
            raise TypeError(
                "first_action='enumerate' needs a probabilistic actor (a ProbabilisticActor "
                f"with a categorical distribution), got {type(policy).__name__}"
            )
        if isinstance(learner_steps, bool) or not isinstance(learner_steps, int):
            raise TypeError(f"learner_steps must be an int, got {learner_steps!r}")
        if learner_steps < 0 or (learner_steps > 0 and tail_policy is None):
            raise ValueError(
                f"learner_steps={learner_steps}: must be >= 0, and > 0 only with a "
                "tail_policy (without one the policy acts on the whole tail already)"
            )
        if learner_branches is not None and (first_action != "enumerate" or learner_steps < 1):
            raise ValueError(
                f"learner_branches={learner_branches} splits the branches of enumerated first "
                "actions between the learner's steps and the tail policy's: it needs "
                f"first_action='enumerate' and learner_steps >= 1, got {first_action!r} and "
                f"{learner_steps}"
            )
        self.policy = policy
        self.learner_steps = learner_steps
        self.learner_branches = learner_branches
        self.explore_steps = explore_steps
        self.first_action = first_action
        self.tail_policy = tail_policy
        self.in_keys = [*policy.in_keys, _ROOT_STEP, _STEP_COUNT]
        if first_action == "enumerate":
            self.in_keys.append(_BRANCH)
        self.out_keys = [*policy.out_keys, EXPLORED]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the action (sampled or greedy per row) and ``"explored"``."""
        mode = exploration_type()
        greedy_policy = self.policy if self.tail_policy is None else self.tail_policy
        if mode in (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN):
            out = greedy_policy(tensordict)
            explored = torch.zeros(out.batch_size, dtype=torch.bool, device=out.device)
            return out.set(EXPLORED, explored)
        needed = [_ROOT_STEP, _STEP_COUNT]
        if self.first_action == "enumerate":
            needed.append(_BRANCH)
        for key in needed:
            if key not in tensordict.keys():
                raise KeyError(
                    f"GreedyTail needs {key!r} to know each row's step within its branch; "
                    "run it through torchrl_grpo.branching (branch_rollout, GroupCollector)"
                )
        t = tensordict.get(_STEP_COUNT).reshape(tensordict.batch_size) - tensordict.get(
            _ROOT_STEP
        ).reshape(tensordict.batch_size)
        # The sampled and the greedy outputs of the learner come from one forward of
        # its network: they differ only in how the action is drawn from the logits.
        with shared_forward(self.policy, include_no_grad=True):
            return self._act(tensordict, t, greedy_policy)

    def _act(
        self, tensordict: TensorDictBase, t: torch.Tensor, greedy_policy: TensorDictModuleBase
    ) -> TensorDictBase:
        """Sample, enumerate or act greedily on each row by its branch-local step ``t``."""
        explored = t < self.explore_steps
        sampled = self.policy(tensordict.clone(False))
        if self.first_action == "enumerate":
            self._enumerate(sampled, tensordict.get(_BRANCH).reshape(t.shape), t == 0)
        if bool(explored.all()):
            return tensordict.update(sampled).set(EXPLORED, explored)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            own = ~explored & (t < self.explore_steps + self.learner_steps)
            if self.learner_branches is not None:
                own = own & (tensordict.get(_BRANCH).reshape(t.shape) < self.learner_branches)
            tail_keys = getattr(self.tail_policy, "out_keys", None)
            if tail_keys is not None and bool((own | explored).all()):
                # The learner acts on every greedy row (a branch's horizon ends within its
                # learner_steps, as in the recipe): all the tail would write is
                # overwritten, so it is not run.
                greedy = self._learner_only(tensordict, tail_keys)
            else:
                greedy = greedy_policy(tensordict.clone(False))
                if bool(own.any()):
                    self._learner_acts(greedy, self.policy(tensordict.clone(False)), own)
        sampled_keys, greedy_keys = set(sampled.keys(True)), set(greedy.keys(True))
        for key in self.policy.out_keys:
            if key not in sampled_keys:
                continue
            a = sampled.get(key)
            if key not in greedy_keys:
                # A scripted tail writes only the action; the rows it acts on are not
                # trained on, so the sampled log-prob and logits may stand there.
                tensordict.set(key, a)
                continue
            b = greedy.get(key)
            rows = explored.reshape(explored.shape + (1,) * (a.ndim - explored.ndim))
            tensordict.set(key, torch.where(rows, a, b))
        return tensordict.set(EXPLORED, explored)

    def _learner_only(self, tensordict: TensorDictBase, tail_keys: list) -> TensorDictBase:
        """What :meth:`_act`'s greedy output is when the learner acts on every greedy row.

        The learner's greedy output under the keys the tail would have written or the
        input holds, cast as :meth:`_learner_acts` casts them; nothing else.
        """
        own = self.policy(tensordict.clone(False))
        greedy = tensordict.clone(False)
        present = set(tensordict.keys(True))
        for key in self.policy.out_keys:
            if key in present:
                greedy.set(key, own.get(key).to(tensordict.get(key).dtype))
            elif key in tail_keys:
                greedy.set(key, own.get(key))
        return greedy

    def _learner_acts(
        self, greedy: TensorDictBase, own: TensorDictBase, rows: torch.Tensor
    ) -> None:
        """Overwrite what the tail policy wrote with the learner's greedy output on ``rows``."""
        greedy_keys = set(greedy.keys(True))
        for key in self.policy.out_keys:
            if key in greedy_keys:
                b = greedy.get(key)
                a = own.get(key).reshape(b.shape).to(b.dtype)
                mask = rows.reshape(rows.shape + (1,) * (a.ndim - rows.ndim))
                greedy.set(key, torch.where(mask, a, b))

    def _enumerate(
        self, sampled: TensorDictBase, branch: torch.Tensor, first: torch.Tensor
    ) -> None:
        """Overwrite the first step's sampled action with ``branch mod n``, and its log-prob."""
        if not bool(first.any()):
            return
        dist = self.policy.build_dist_from_params(sampled)
        action_key = self.policy.dist_sample_keys[0]
        action = sampled.get(action_key)
        n = dist.logits.shape[-1]
        index = branch.remainder(n)
        if action.shape == dist.logits.shape:  # one-hot actions
            forced = torch.nn.functional.one_hot(index, n).to(action.dtype)
            rows = first.unsqueeze(-1)
        else:
            forced = index.to(action.dtype).reshape(action.shape)
            rows = first.reshape(action.shape)
        action = torch.where(rows, forced, action)
        sampled.set(action_key, action)
        for key in getattr(self.policy, "log_prob_keys", []):
            if key in sampled.keys(True):
                sampled.set(key, dist.log_prob(action).reshape(sampled.get(key).shape))
