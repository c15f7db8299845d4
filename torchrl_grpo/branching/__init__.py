"""Branch groups: G rollouts of a policy from one exact snapshot, run by TorchRL workers.

A group is G branches that all start from bitwise the same simulator state (a
*root*) and differ only through the policy's samples. Roll out groups from R roots
at once with :func:`branch_rollout` (one ``[R, G, T]`` tensordict), continue an
episode from a chosen branch with :func:`multi_turn_rollout`, or stream groups for
training with :class:`GroupCollector`. Roots come from episode starts
(:func:`reset_roots`), decision points along a trunk (:func:`trunk_roots`) or
stored trajectories (:func:`roots_from_trajectories`). :class:`LookaheadPolicy` uses
the same snapshots to plan: every action from the current state, then a base policy.
See ``docs/branching.md``.
"""

from torchrl_grpo.branching.branch_env import make_branch_env, shutdown_env
from torchrl_grpo.branching.continuation import MultiTurnResult, multi_turn_rollout, select_branches
from torchrl_grpo.branching.group_collector import GroupCollector
from torchrl_grpo.branching.group_plots import plot_group
from torchrl_grpo.branching.keys import BRANCH, BRANCH_RETURN, GROUP_ID, MASK, STATE
from torchrl_grpo.branching.lookahead import LookaheadPolicy
from torchrl_grpo.branching.rollout import branch_rollout, final_states
from torchrl_grpo.branching.root_builders import (
    make_roots,
    reset_roots,
    roots_from_trajectories,
    trunk_roots,
)
from torchrl_grpo.branching.roots import RootSource, StoredRoots

__all__ = [
    "BRANCH",
    "BRANCH_RETURN",
    "GROUP_ID",
    "MASK",
    "STATE",
    "GroupCollector",
    "LookaheadPolicy",
    "MultiTurnResult",
    "RootSource",
    "StoredRoots",
    "branch_rollout",
    "final_states",
    "make_branch_env",
    "make_roots",
    "multi_turn_rollout",
    "plot_group",
    "reset_roots",
    "roots_from_trajectories",
    "select_branches",
    "shutdown_env",
    "trunk_roots",
]
