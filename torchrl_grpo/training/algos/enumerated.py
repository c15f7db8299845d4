"""Enumerated groups (every first action of a root tried): their replay and their weights.

With ``algo.first_action=enumerate`` and a scripted ``algo.tail_policy``, a group scores
every action of its root under a fixed base policy: the advantages do not depend on the
policy that collected them, so old groups stay valid targets (:func:`make_replay`), and
each action's term can be weighed by the probability the policy gives it
(:func:`policy_weighted`).
"""

from __future__ import annotations

from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer

__all__ = ["make_replay", "policy_weighted", "replay_rows"]


def make_replay(algo: DictConfig) -> ReplayBuffer | None:
    """The FIFO buffer of the trained steps of ``algo.replay_groups`` groups, or ``None``.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"replay_groups": 10, "group_size": 5, "explore_steps": 1})
        >>> make_replay(cfg).storage.max_size
        50
    """
    rows = replay_rows(algo)
    return None if rows is None else ReplayBuffer(storage=LazyTensorStorage(rows), batch_size=None)


def replay_rows(algo: DictConfig) -> int | None:
    """Trained steps the replay holds: one per explored step of each of the groups' branches.

    Example:
        >>> from omegaconf import OmegaConf
        >>> replay_rows(OmegaConf.create({"replay_groups": 4, "group_size": 5,
        ...                               "explore_steps": 1}))
        20
    """
    groups = algo.get("replay_groups")
    if groups is None:
        return None
    return int(groups) * int(algo.group_size) * int(algo.explore_steps)


def policy_weighted(data: TensorDictBase, n_actions: int) -> TensorDictBase:
    """Scale each enumerated step's advantage by ``n * pi(a|s)`` (``algo.action_weights``).

    The clipped surrogate is linear in the advantage, so this weighs each action's
    term by the probability the policy gives it: the sum over a group is then
    ``n`` times the expected surrogate over all actions of its root.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict(advantage=torch.ones(2, 1),
        ...                   action_log_prob=torch.tensor([0.5, 0.25]).log(), batch_size=[2])
        >>> policy_weighted(data, 4)["advantage"].squeeze(-1)
        tensor([2., 1.])
    """
    weight = n_actions * data.get("action_log_prob").exp()
    advantage = data.get("advantage")
    weighted = advantage * weight.reshape(advantage.shape)
    return data.clone(recurse=False).set("advantage", weighted)
