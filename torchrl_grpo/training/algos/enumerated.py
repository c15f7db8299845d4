"""Enumerated groups (every first action of a root tried): their replay and their weights.

With ``algo.first_action=enumerate`` and a scripted ``algo.tail_policy``, a group scores
every action of its root under a fixed base policy: the advantages do not depend on the
policy that collected them, so old groups stay valid targets (:func:`make_replay`), and
each action's term can be weighed by the probability the policy gives it
(:func:`policy_weighted`), or distilled as a target distribution per root
(:func:`distill_targets`).
"""

from __future__ import annotations

from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_grpo.branching import GROUP_ID
from torchrl_grpo.objectives import group_softmax_target

__all__ = [
    "DISTILL_WEIGHT",
    "check_distill",
    "check_replay_targets",
    "distill_targets",
    "make_replay",
    "policy_weighted",
    "replay_rows",
]

#: Each trained step's weight in its root's distillation target (``algo.distill_coeff``).
DISTILL_WEIGHT = "distill_weight"


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


def check_distill(algo: DictConfig) -> None:
    """Refuse ``algo.distill_*`` settings whose target would not be one root's actions.

    Raises:
        ValueError: a negative or non-finite coefficient or temperature; or a positive
            coefficient without ``algo.first_action=enumerate`` and
            ``algo.explore_steps=1`` (the rows of a group must be the actions of one state).

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_distill(OmegaConf.create({"distill_coeff": 1.0, "distill_temperature": 0.1,
        ...                                 "first_action": "sample", "explore_steps": 1}))
        Traceback (most recent call last):
        ...
        ValueError: algo.distill_coeff=1.0 distils each root's enumerated actions: set algo.first_action=enumerate and algo.explore_steps=1
    """  # noqa: E501 - a doctest's expected output is one line
    coeff, tau = float(algo.distill_coeff), float(algo.distill_temperature)
    if not 0 <= coeff < float("inf"):
        raise ValueError(f"algo.distill_coeff must be a finite number >= 0, got {coeff}")
    if not 0 <= tau < float("inf"):
        raise ValueError(f"algo.distill_temperature must be a finite number >= 0, got {tau}")
    if coeff > 0 and (str(algo.first_action) != "enumerate" or algo.explore_steps != 1):
        raise ValueError(
            f"algo.distill_coeff={coeff} distils each root's enumerated actions: set "
            "algo.first_action=enumerate and algo.explore_steps=1"
        )


def distill_targets(data: TensorDictBase, temperature: float) -> TensorDictBase:
    """``data`` (a batch's trained steps) with :data:`DISTILL_WEIGHT`, its groups' targets.

    The weight is computed when the steps are collected, so replayed steps keep the
    target of their own group (group ids are reused across batches).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict(advantage=torch.tensor([[0.0], [1.0]]),
        ...                   group_id=torch.tensor([3, 3]), batch_size=[2])
        >>> distill_targets(data, 0.0)["distill_weight"].squeeze(-1)
        tensor([0., 1.])
    """
    weight = group_softmax_target(data.get("advantage"), data.get(GROUP_ID), temperature)
    return data.set(DISTILL_WEIGHT, weight)


def check_replay_targets(saved: DictConfig, algo: DictConfig, source: str = "") -> None:
    """Refuse a resume whose replayed steps hold targets this config does not, or lack them.

    A replay stores :data:`DISTILL_WEIGHT` with each step when ``algo.distill_coeff > 0``:
    the first write of steps with other keys would fail mid-run.

    Args:
        saved: the checkpoint's ``algo`` config.
        algo: this run's ``algo`` config.
        source: the checkpoint's path, for the error.

    Raises:
        ValueError: distillation is on in one and off in the other.

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_replay_targets(OmegaConf.create({}), OmegaConf.create({"distill_coeff": 1.0}))
        Traceback (most recent call last):
        ...
        ValueError: resume= replays steps stored without distillation targets and this config has algo.distill_coeff=1.0: resume with the run's algo.distill_coeff (0 or > 0)
    """  # noqa: E501 - a doctest's expected output is one line
    saved_on = float(saved.get("distill_coeff", 0.0)) > 0
    coeff = float(algo.distill_coeff)
    if saved_on != (coeff > 0):
        stored = "with" if saved_on else "without"
        raise ValueError(
            f"resume={source} replays steps stored {stored} distillation targets and this "
            f"config has algo.distill_coeff={coeff}: resume with the run's algo.distill_coeff "
            "(0 or > 0)"
        )
