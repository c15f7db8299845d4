"""Which engine runs a rollout's branches: one per kind of env.

- A batched simulator (an env marked ``batched_worlds = True``, as
  :class:`~torchrl_grpo.envs.TensorHighwayEnv`): the branches are rows of one batched
  rollout on its device (:mod:`~torchrl_grpo.branching.batched_worlds`).
- A snapshot env (highway-env, CartPole, ...): the branches run on its worker slots.
  On a :class:`~torchrl_grpo.branching.BranchParallelEnv` each worker runs whole
  branches with its own copy of the policy (:mod:`~torchrl_grpo.branching.worker_branches`).
  Where the policy runs in this process (a plain env, a ``SerialEnv``, a policy that
  cannot be sent to the workers, or ``env.whole_branches = False``) the slots step
  together, the policy called here once per step (:mod:`~torchrl_grpo.branching.lockstep`).
"""

from __future__ import annotations

from tensordict import TensorDictBase

from torchrl_grpo.branching.batched_worlds import run_batched_branches
from torchrl_grpo.branching.env_slots import EnvSlots, has_batched_worlds
from torchrl_grpo.branching.lockstep import run_branches
from torchrl_grpo.branching.rollout_rows import BranchRun, Policy
from torchrl_grpo.branching.worker_branches import run_whole_branches

__all__ = ["run_on"]


def run_on(
    slots: EnvSlots, policy: Policy, states: TensorDictBase, horizon: int, **kwargs
) -> BranchRun:
    """Run branches on ``slots``' env: rows of one rollout for a batched simulator, else slots.

    The arguments are :func:`~torchrl_grpo.branching.batched_worlds.run_batched_branches`'
    (``kwargs``: ``group_id``, ``branch``, ``root_step``, ``keep``, ``exploration_type``).

    Example:
        >>> import torch
        >>> from torchrl_grpo.envs import TensorHighwayEnv
        >>> env = TensorHighwayEnv(num_envs=2, seed=0)
        >>> zero = torch.zeros(2, dtype=torch.int64)
        >>> idle = lambda td: td.set("action", torch.ones(2, dtype=torch.int64))
        >>> run = run_on(EnvSlots(env), idle, env.get_state(), 3, group_id=zero, branch=zero,
        ...              root_step=zero)
        >>> run.lengths.tolist()
        [3, 3]
    """
    if has_batched_worlds(slots.env):
        return run_batched_branches(slots.env, policy, states, horizon, **kwargs)
    if slots.whole_branches:
        run = run_whole_branches(slots, policy, states, horizon, **kwargs)
        if run is not None:
            return run
    return run_branches(slots, policy, states, horizon, **kwargs)
