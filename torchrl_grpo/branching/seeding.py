"""The simulator seed of each branch when branches draw their own randomness.

highway-env draws almost no random numbers after a reset, so branches restored from
one state differ only through the policy's samples. intersection-v0 is the
exception: it spawns traffic from the env's generator at every step. With
``rng="per_branch"`` the rollout functions restart each branch's generator (through
:meth:`~torchrl_grpo.envs.SnapshotEnv.reseed_state`) from :func:`branch_seed`, which
makes its traffic its own, at the price of branches that no longer share their
future traffic.
"""

from __future__ import annotations

import numpy as np

__all__ = ["branch_seed"]

_SEED_BITS = 63  # fits an int64 tensor and numpy's non-negative seeds


def branch_seed(seed: int, group_id: int, branch: int) -> int:
    """The simulator seed of one branch: ``(seed, group_id, branch)`` mixed into one int.

    numpy's ``SeedSequence`` mixes the three, so neighbouring groups and branches get
    unrelated streams. Reproduce a branch by hand with
    ``env.reseed_state(root_state, branch_seed(seed, group_id, branch))``.

    Args:
        seed: the rollout's ``seed`` argument (non-negative).
        group_id: the branch's group id.
        branch: the branch's index in its group.

    Returns:
        A non-negative int below ``2**63``.

    Example:
        >>> a = branch_seed(0, 3, 1)
        >>> a == branch_seed(0, 3, 1), a == branch_seed(0, 3, 2), 0 <= a < 2**63
        (True, False, True)
    """
    words = np.random.SeedSequence([int(seed), int(group_id), int(branch)]).generate_state(
        2, np.uint32
    )
    return (int(words[0]) | int(words[1]) << 32) & ((1 << _SEED_BITS) - 1)
