"""Names of the entries that branch rollouts add to TorchRL's per-step data.

Every entry is shaped like the step batch (``[R, G, T]`` for a branch rollout), so
the data can be flattened, masked or written to a replay buffer like collector
output. ``group_id`` is the key :class:`torchrl.objectives.llm.MCAdvantage` groups by
(``prompt_key="group_id"``) and, with ``branch`` and ``mask``, what
:class:`~torchrl_grpo.objectives.GroupRelativeAdvantage` reads.
"""

from __future__ import annotations

GROUP_ID = "group_id"
"""int64: one id per root, unique across a whole collection."""
BRANCH = "branch"
"""int64: the branch's index within its group, ``0 .. G - 1``."""
ROOT_STEP = "root_step"
"""int64: how many steps into its episode the root state is."""
STEP_COUNT = "step_count"
"""int64 ``[..., 1]``: the episode step of the current observation (``root_step + t``),
with the shape TorchRL's :class:`~torchrl.envs.StepCounter` uses."""
MASK = "mask"
"""bool: ``True`` on steps the branch actually took; ``False`` after it ended."""
BRANCH_RETURN = "branch_return"
"""float32 ``[..., 1]``: the undiscounted sum of the branch's valid rewards, repeated on
every step of the branch."""
TRAJ_IDS = ("collector", "traj_ids")
"""int64: a unique id per branch (``group_id * G + branch``), as TorchRL collectors write."""
STATE = "state"
"""The simulator state before the step (and ``("next", "state")`` after it), written
when states are requested: the key :class:`~torchrl_grpo.envs.SnapshotEnv` restores
from and, built with ``return_state=True``, returns after every reset and step."""

__all__ = [
    "BRANCH",
    "BRANCH_RETURN",
    "GROUP_ID",
    "MASK",
    "ROOT_STEP",
    "STATE",
    "STEP_COUNT",
    "TRAJ_IDS",
]
