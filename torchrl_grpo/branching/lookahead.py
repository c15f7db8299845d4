"""A planner that uses snapshots for search: try every action, keep the best.

:class:`LookaheadPolicy` is the rollout algorithm (Bertsekas) over a base policy: from
the current state it branches once per action, takes that action, follows the base
policy for the rest of the horizon and acts with the action whose branch earned the
most reward. It is the exact version of what a group with enumerated first actions and
a scripted tail measures (``algo.first_action=enumerate algo.tail_policy=...``), so it
shows how far a learner trained on those groups could go.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_grpo.branching.env_slots import has_batched_worlds
from torchrl_grpo.branching.keys import BRANCH, MASK, ROOT_STEP, STATE, STEP_COUNT
from torchrl_grpo.branching.rollout import branch_rollout
from torchrl_grpo.branching.root_builders import as_roots
from torchrl_grpo.envs.core.bits import to_bits

__all__ = ["ActionThenBase", "LookaheadPolicy", "best_actions", "branch_returns"]


def branch_returns(data: TensorDictBase) -> torch.Tensor:
    """Each branch's return, ``[..., G]``, of a ``[..., G, T]`` branch rollout.

    Summed step by step in float64, the order of a sequential sum of the rewards; the
    steps after a branch ended (``mask`` false) count nothing.

    Example:
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"mask": torch.tensor([[True, True], [True, False]]),
        ...                    ("next", "reward"): torch.ones(2, 2, 1)}, batch_size=[2, 2])
        >>> branch_returns(data).tolist()
        [2.0, 1.0]
    """
    mask = data.get(MASK)
    reward = data.get(("next", "reward")).reshape(mask.shape).double()
    scores = torch.zeros(mask.shape[:-1], dtype=torch.float64, device=reward.device)
    for t in range(mask.shape[-1]):
        scores += torch.where(mask[..., t], reward[..., t], 0.0)
    return scores


def best_actions(scores: torch.Tensor) -> torch.Tensor:
    """The planner's choice: the action of the highest branch return, per row.

    The one selection rule of every lookahead path (a state at a time, or all of an
    evaluation's episodes at once): ties go to the lowest action index.

    Args:
        scores: branch returns ``[..., n_actions]`` (:meth:`LookaheadPolicy.returns`).

    Returns:
        int64 actions ``[...]``.

    Example:
        >>> best_actions(torch.tensor([[1.0, 3.0, 3.0], [2.0, 0.0, 1.0]])).tolist()
        [1, 0]
    """
    # argmax returns the first maximum: ties go to the lowest action index.
    return scores.argmax(-1).to(torch.int64)


class LookaheadPolicy(TensorDictModuleBase):
    """Act with the action whose ``horizon``-step branch, then ``base``, earns the most.

    The policy reads the simulator state from its input (``"state"``, written at every
    step by envs built with ``return_state=True``), so it works in ``env.rollout`` and
    in :func:`~torchrl_grpo.training.evaluate` like any policy. It restores that state
    into its own ``env`` once per action: the env being driven is never touched. A
    branch's score is its undiscounted reward; a branch ends early when its episode
    does (a crash forfeits the rest of the horizon). Ties go to the lowest action index.

    Args:
        env: a snapshot env of the same scenario and config, used only for planning.
        base: the policy the branches follow after their first action (for example a
            scripted policy from :func:`~torchrl_grpo.modules.make_scripted_policy`).
        horizon: steps per branch (>= 1; 1 compares the immediate rewards only).
        n_actions: actions to try, ``0 .. n_actions - 1``; default: ``env.action_spec.n``.
        import_state: maps the driven env's states (``[N]``, or one) to ``env``'s
            states ``[N]``, when they are of another kind: with a
            :class:`~torchrl_grpo.envs.TensorHighwayEnv` planning for a driven
            :class:`~torchrl_grpo.envs.HighwayEnv`, its ``state_from_highway``. The
            branches then run as rows of one batched rollout of the tensor simulator,
            which steps as highway-env does.

    Attributes:
        frames: env steps simulated for planning so far.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> from torchrl_grpo.modules import make_scripted_policy
        >>> env = HighwayEnv("highway-fast-v0", seed=0, return_state=True)
        >>> planner = LookaheadPolicy(HighwayEnv("highway-fast-v0"),
        ...                           make_scripted_policy("slower"), horizon=2)
        >>> data = env.rollout(3, planner)
        >>> data["action"].shape, planner.frames <= 3 * 5 * 2
        (torch.Size([3]), True)

        Planning on the tensor simulator for highway-env, with the same scores up to
        the float32 rewards' rounding:

        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> sim = TensorHighwayEnv("highway-fast-v0", num_envs=5)
        >>> fast = LookaheadPolicy(sim, make_scripted_policy("slower"), horizon=2,
        ...                        import_state=sim.state_from_highway)
        >>> torch.allclose(fast.returns(data[-1]), planner.returns(data[-1]), atol=1e-5)
        True
    """

    def __init__(
        self,
        env: EnvBase,
        base: TensorDictModuleBase,
        horizon: int,
        n_actions: int | None = None,
        import_state: Callable[[TensorDictBase], TensorDictBase] | None = None,
    ) -> None:
        super().__init__()
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon must be an int >= 1, got {horizon!r}")
        if not getattr(env, "_supports_set_state", False):
            raise TypeError(
                f"LookaheadPolicy plans by restoring snapshots; {type(env).__name__} cannot "
                "reset(set_state=True)"
            )
        if n_actions is None:
            n_actions = getattr(env.action_spec, "n", None)
            if n_actions is None:
                raise ValueError("the env's actions are not discrete: pass n_actions")
        self.env = env
        self.base = base
        self.horizon = horizon
        self.n_actions = int(n_actions)
        self.frames = 0
        self.import_state = import_state
        self._branch_policy = ActionThenBase(base)
        self.in_keys = [STATE, *base.in_keys]
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the planned ``"action"``; a batched input is planned row by row."""
        if STATE not in tensordict.keys():
            raise KeyError(
                f"LookaheadPolicy reads the simulator state from {STATE!r}: build the env it "
                "drives with return_state=True"
            )
        if tensordict.batch_dims == 0:
            return tensordict.set("action", self._plan(tensordict))
        flat = tensordict.reshape(-1)
        if has_batched_worlds(self.env):
            # Every row's branches are rows of one batched rollout.
            actions = best_actions(self.returns(flat))
        else:
            actions = torch.stack([self._plan(flat[i]) for i in range(flat.shape[0])])
        return tensordict.set("action", actions.reshape(tensordict.batch_size))

    def returns(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The branch return of every action from the state(s) in ``tensordict``.

        Returns:
            ``[n_actions]`` for an unbatched input, ``[N, n_actions]`` for ``N`` rows.
        """
        scores = branch_returns(self.branches(tensordict))
        return scores if tensordict.batch_dims else scores[0]

    def branches(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The branches from the state(s) in ``tensordict``: ``[N, n_actions, horizon]``.

        Every action's branch (that action, then ``base``'s) as :func:`branch_rollout`
        returns it, an unbatched input as one row; their steps count in :attr:`frames`.
        """
        state = tensordict.get(STATE)
        _check_fresh(tensordict, state)
        if self.import_state is not None:
            state = self.import_state(state)
        data = branch_rollout(
            self.env, self._branch_policy, as_roots(state), self.n_actions, self.horizon
        )
        self.frames += int(data.get(MASK).sum())
        return data

    def _plan(self, tensordict: TensorDictBase) -> torch.Tensor:
        return best_actions(self.returns(tensordict))


class ActionThenBase(TensorDictModuleBase):
    """Branch ``b`` takes action ``b`` at its first step, then ``base`` acts.

    The policy of the planner's branches (and of any group that scores every action
    of a root under a fixed base policy): a row whose ``step_count`` is its
    ``root_step`` plays its ``branch`` index, every later row ``base``'s action.

    Args:
        base: the policy after the first step (it writes ``"action"``).

    Example:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> base = TensorDictModule(lambda obs: torch.zeros(obs.shape[0], dtype=torch.int64),
        ...                         ["observation"], ["action"])
        >>> td = TensorDict(observation=torch.zeros(3, 2), branch=torch.tensor([2, 3, 4]),
        ...                 root_step=torch.tensor([5, 5, 5]),
        ...                 step_count=torch.tensor([[5], [6], [5]]), batch_size=[3])
        >>> ActionThenBase(base)(td)["action"].tolist()
        [2, 0, 4]
    """

    def __init__(self, base: TensorDictModuleBase) -> None:
        super().__init__()
        self.base = base
        self.in_keys = [*base.in_keys, BRANCH, ROOT_STEP, STEP_COUNT]
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write each row's action: its branch index at the first step, else ``base``'s."""
        shape = tensordict.batch_size
        step = tensordict.get(STEP_COUNT).reshape(shape)
        first = step == tensordict.get(ROOT_STEP).reshape(shape)
        action = self.base(tensordict).get("action")
        branch = tensordict.get(BRANCH).reshape(action.shape).to(action.dtype)
        return tensordict.set("action", torch.where(first.reshape(action.shape), branch, action))


def _check_fresh(tensordict: TensorDictBase, state: TensorDictBase) -> None:
    """Refuse a state that is not the one the input's observation was read from.

    An env built without ``return_state`` writes its state at reset only, and a
    rollout carries that state to every later step: planning from it would silently
    plan from the episode's start.
    """
    if _stored_observation_differs(tensordict, state) or _ego_position_differs(tensordict, state):
        raise ValueError(
            f"the input's {STATE!r} is not the state its observation comes from (a stale "
            "state, carried from the reset): build the env it drives with return_state=True"
        )


def _stored_observation_differs(tensordict: TensorDictBase, state: TensorDictBase) -> bool:
    # A HighwayEnv state stores the observation it was taken with.
    stored = state.get(("output", "observation"), None)
    if stored is None or "observation" not in tensordict.keys():
        return False
    return not torch.equal(to_bits(tensordict.get("observation")), stored)


def _ego_position_differs(tensordict: TensorDictBase, state: TensorDictBase) -> bool:
    # A tensor simulator's state holds the ego in vehicle slot 0.
    x, y = state.get(("vehicles", "x"), None), state.get(("vehicles", "y"), None)
    if x is None or y is None or "ego_position" not in tensordict.keys():
        return False
    seen = tensordict.get("ego_position")
    ego = torch.stack([x[..., 0], y[..., 0]], -1).to(seen.dtype)
    return ego.shape != seen.shape or not torch.equal(ego, seen)
