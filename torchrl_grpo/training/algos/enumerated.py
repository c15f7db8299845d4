"""Enumerated groups (every first action of a root tried): their replay and their weights.

With ``algo.first_action=enumerate`` and a scripted ``algo.tail_policy``, a group scores
every action of its root under a fixed base policy: the advantages do not depend on the
policy that collected them, so old groups stay valid targets (:func:`make_replay`), and
each action's term can be weighed by the probability the policy gives it
(:func:`policy_weighted`), or fitted per root (:func:`distill_targets`, the group fit of
``algo.group_fit_coeff``).

The highway recipes' group fit is the regression of each root's centred logits on its
actions' advantages (``algo.group_fit_loss=regression``); merge-v0's is the policy's
expected regret at each root (``regret``, :class:`~torchrl_grpo.objectives.GroupRegretLoss`).
Every root weighs alike. Other fits and weightings are registered by name
(:func:`register_group_fit`, :func:`register_group_fit_weighting`):
``torchrl_grpo.experimental``, which the core never imports, adds the cross-entropy fit
and the spread weighting of ``algo=grpo_lab``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.objectives import LossModule

from torchrl_grpo.branching.keys import GROUP_ID
from torchrl_grpo.objectives.group_targets import group_best_set, group_regret
from torchrl_grpo.objectives.regression import AdvantageRegressionLoss
from torchrl_grpo.objectives.regret_fit import GroupRegretLoss
from torchrl_grpo.training.choices import choice_enum

__all__ = [
    "BRANCH_CRASHED",
    "DISTILL_TARGET",
    "DISTILL_WEIGHT",
    "GROUP_FITS",
    "GROUP_FIT_WEIGHTINGS",
    "ActionWeights",
    "ActionWeightsName",
    "GroupFit",
    "branch_crashed",
    "check_distill",
    "check_replay_targets",
    "distill_targets",
    "make_group_fit_loss",
    "make_replay",
    "policy_weighted",
    "register_group_fit",
    "register_group_fit_weighting",
    "replay_rows",
]

#: Each trained step's weight in its root's distillation target (``algo.group_fit_coeff``).
DISTILL_WEIGHT = "distill_weight"
#: Whether each trained step's branch ended in a crash (the env terminated it): the label
#: of a crash head (``model.crash_head``).
BRANCH_CRASHED = "branch_crashed"
#: Each trained step's target as its group gave it: its advantage for
#: ``algo.group_fit_loss=regression`` (the surrogate's advantage may be reweighted), its
#: regret for ``regret``.
DISTILL_TARGET = "distill_target"

#: Weight of each enumerated first action in the objective (``algo.action_weights``):
#: once each, or ``n * pi(a|s)`` (the expected clipped surrogate over all actions).
ActionWeights = Literal["uniform", "policy"]
ActionWeightsName = choice_enum(
    "ActionWeightsName",
    ActionWeights,
    "Weight of an enumerated first action in the objective.",
    module=__name__,
)


@dataclass(frozen=True)
class GroupFit:
    """One ``algo.group_fit_loss``: the rows' targets and the loss that fits them.

    Attributes:
        targets: ``(data, temperature) -> weight``: each trained row's weight in its
            root's fit (``[N, 1]``, like the advantage); it may also write the row's
            target into ``data`` (the regression's :data:`DISTILL_TARGET`).
        make_loss: ``(policy, coeff, temperature) -> loss``: the term beside the
            surrogate, reading the rows' weights under :data:`DISTILL_WEIGHT`.

    Example:
        >>> GROUP_FITS["regression"].make_loss.__name__
        '_regression_loss'
    """

    targets: Callable[[TensorDictBase, float], torch.Tensor]
    make_loss: Callable[[nn.Module, float, float], LossModule]


def _regression_targets(data: TensorDictBase, temperature: float) -> torch.Tensor:
    advantage = data.get("advantage")
    data.set(DISTILL_TARGET, advantage.clone())
    return torch.ones_like(advantage)


def _regression_loss(policy: nn.Module, coeff: float, temperature: float) -> LossModule:
    return AdvantageRegressionLoss(policy, coeff=coeff, temperature=temperature)


def _regret_targets(data: TensorDictBase, temperature: float) -> torch.Tensor:
    # The temperature plays no part: the regret is in return units. The weight is the
    # row's share of its group's best set, the anchor's hard target.
    advantage, group_id = data.get("advantage"), data.get(GROUP_ID)
    data.set(DISTILL_TARGET, group_regret(advantage, group_id))
    return group_best_set(advantage, group_id)


def _regret_loss(policy: nn.Module, coeff: float, temperature: float) -> LossModule:
    return GroupRegretLoss(policy, coeff=coeff)


#: The group fits by ``algo.group_fit_loss`` (:func:`register_group_fit` adds one).
GROUP_FITS: dict[str, GroupFit] = {
    "regression": GroupFit(_regression_targets, _regression_loss),
    "regret": GroupFit(_regret_targets, _regret_loss),
}
#: The root weightings by ``algo.group_fit_weighting`` other than ``uniform`` (every root
#: alike): ``(advantage, group_id) -> factor`` on each row's weight
#: (:func:`register_group_fit_weighting` adds one).
GROUP_FIT_WEIGHTINGS: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {}


def register_group_fit(name: str, fit: GroupFit) -> GroupFit:
    """Makes ``fit`` the group fit of ``algo.group_fit_loss=name``.

    Raises:
        ValueError: another fit has that name.

    Example:
        >>> fit = GroupFit(GROUP_FITS["regression"].targets, GROUP_FITS["regression"].make_loss)
        >>> register_group_fit("my_fit", fit) is GROUP_FITS["my_fit"]
        True
        >>> del GROUP_FITS["my_fit"]  # leave the registry as it was
    """
    return _register(GROUP_FITS, name, fit, "algo.group_fit_loss")


def register_group_fit_weighting(
    name: str, weighting: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """Makes ``weighting`` the root weighting of ``algo.group_fit_weighting=name``.

    Raises:
        ValueError: another weighting has that name, or the name is ``uniform``.

    Example:
        >>> def doubled(advantage, group_id):
        ...     return torch.full_like(advantage, 2.0)
        >>> register_group_fit_weighting("doubled", doubled) is doubled
        True
        >>> del GROUP_FIT_WEIGHTINGS["doubled"]  # leave the registry as it was
    """
    if name == "uniform":
        raise ValueError("algo.group_fit_weighting=uniform is the core's: weigh roots alike")
    return _register(GROUP_FIT_WEIGHTINGS, name, weighting, "algo.group_fit_weighting")


def _register(registry: dict, name: str, entry: object, key: str) -> object:
    taken = registry.get(name)
    if taken is not None and taken != entry:
        raise ValueError(f"{key}={name} is taken")
    registry[name] = entry
    return entry


def _unknown(key: str, value: str, known: list[str]) -> ValueError:
    return ValueError(
        f"{key} must be {' or '.join(repr(k) for k in known)}, got {value!r} (the "
        "experimental ones are algo=grpo_lab's: import torchrl_grpo.experimental)"
    )


def make_replay(algo: DictConfig, branches: int | None = None) -> ReplayBuffer | None:
    """The FIFO buffer of the trained steps of ``algo.replay_groups`` groups, or ``None``.

    ``branches``: the trained branches of a group (:func:`replay_rows`).

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"replay_groups": 10, "group_size": 5, "explore_steps": 1})
        >>> make_replay(cfg).storage.max_size
        50
    """
    rows = replay_rows(algo, branches)
    return None if rows is None else ReplayBuffer(storage=LazyTensorStorage(rows), batch_size=None)


def replay_rows(algo: DictConfig, branches: int | None = None) -> int | None:
    """Trained steps the replay holds: one per explored step of each of the groups' branches.

    ``branches``: how many of a group's branches are trained (``None``: all of
    ``algo.group_size``).

    Example:
        >>> from omegaconf import OmegaConf
        >>> replay_rows(OmegaConf.create({"replay_groups": 4, "group_size": 5,
        ...                               "explore_steps": 1}))
        20
    """
    groups = algo.get("replay_groups")
    if groups is None:
        return None
    trained = int(algo.group_size) if branches is None else int(branches)
    return int(groups) * trained * int(algo.explore_steps)


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


def branch_crashed(batch: TensorDictBase, mask_key: str = "mask") -> torch.Tensor:
    """``[R, G, T]``: on every step of a branch, whether the env terminated the branch.

    Example:
        >>> from tensordict import TensorDict
        >>> batch = TensorDict({"mask": torch.tensor([[[True, True], [True, False]]]),
        ...                     ("next", "terminated"): torch.tensor([[[[False], [True]],
        ...                                                            [[False], [True]]]])},
        ...                    batch_size=[1, 2, 2])
        >>> branch_crashed(batch).tolist()  # the second's terminated flag is past its end
        [[[True, True], [False, False]]]
    """
    mask = batch.get(mask_key)
    terminated = batch.get(("next", "terminated")).reshape(mask.shape) & mask
    return terminated.any(-1, keepdim=True).expand(mask.shape)


def check_distill(algo: DictConfig) -> None:
    """Refuse ``algo.distill_*`` settings whose target would not be one root's actions.

    Raises:
        ValueError: a negative or non-finite coefficient or temperature; or a positive
            coefficient without ``algo.first_action=enumerate`` and
            ``algo.explore_steps=1`` (the rows of a group must be the actions of one state).

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_distill(OmegaConf.create({"group_fit_coeff": 1.0, "group_fit_temperature": 0.1,
        ...                                 "first_action": "sample", "explore_steps": 1}))
        Traceback (most recent call last):
        ...
        ValueError: algo.group_fit_coeff=1.0 distils each root's enumerated actions: set algo.first_action=enumerate and algo.explore_steps=1
    """  # noqa: E501 - a doctest's expected output is one line
    coeff, tau = float(algo.group_fit_coeff), float(algo.group_fit_temperature)
    if not 0 <= coeff < float("inf"):
        raise ValueError(f"algo.group_fit_coeff must be a finite number >= 0, got {coeff}")
    if not 0 <= tau < float("inf"):
        raise ValueError(f"algo.group_fit_temperature must be a finite number >= 0, got {tau}")
    if str(algo.get("group_fit_loss", "regression")) == "regression" and tau == 0:
        raise ValueError(
            "algo.group_fit_loss=regression reads the logits as advantages / "
            "algo.group_fit_temperature: set a temperature > 0 (e.g. 0.1)"
        )
    if coeff > 0 and (str(algo.first_action) != "enumerate" or algo.explore_steps != 1):
        raise ValueError(
            f"algo.group_fit_coeff={coeff} distils each root's enumerated actions: set "
            "algo.first_action=enumerate and algo.explore_steps=1"
        )


def distill_targets(
    data: TensorDictBase,
    temperature: float,
    weighting: str = "uniform",
    loss: str = "regression",
) -> TensorDictBase:
    """``data`` (a batch's trained steps) with its groups' targets for the group fit.

    The targets are computed when the steps are collected, so replayed steps keep the
    target of their own group (group ids are reused across batches). With
    ``loss="regression"`` (the recipes'), :data:`DISTILL_WEIGHT` is 1 and
    :data:`DISTILL_TARGET` holds the row's advantage; the other fits and weightings are
    those registered (:data:`GROUP_FITS`, :data:`GROUP_FIT_WEIGHTINGS`).

    Raises:
        ValueError: a fit or a weighting that is not registered, naming it.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> data = TensorDict(advantage=torch.tensor([[0.0], [1.0], [2.0], [2.0]]),
        ...                   group_id=torch.tensor([3, 3, 4, 4]), batch_size=[4])
        >>> out = distill_targets(data, 0.1)
        >>> out["distill_weight"].squeeze(-1), out["distill_target"].squeeze(-1)
        (tensor([1., 1., 1., 1.]), tensor([0., 1., 2., 2.]))
    """
    fit = GROUP_FITS.get(loss)
    if fit is None:
        raise _unknown("loss", loss, sorted(GROUP_FITS))
    weight = fit.targets(data, temperature)
    if weighting != "uniform":
        factor = GROUP_FIT_WEIGHTINGS.get(weighting)
        if factor is None:
            raise _unknown("weighting", weighting, ["uniform", *sorted(GROUP_FIT_WEIGHTINGS)])
        weight = weight * factor(data.get("advantage"), data.get(GROUP_ID))
    return data.set(DISTILL_WEIGHT, weight)


def check_replay_targets(saved: DictConfig, algo: DictConfig, source: str = "") -> None:
    """Refuse a resume whose replayed steps hold targets this config does not, or lack them.

    A replay stores :data:`DISTILL_WEIGHT` with each step when ``algo.group_fit_coeff > 0``:
    the first write of steps with other keys would fail mid-run.

    Args:
        saved: the checkpoint's ``algo`` config.
        algo: this run's ``algo`` config.
        source: the checkpoint's path, for the error.

    Raises:
        ValueError: distillation is on in one and off in the other.

    Example:
        >>> from omegaconf import OmegaConf
        >>> check_replay_targets(OmegaConf.create({}), OmegaConf.create({"group_fit_coeff": 1.0}))
        Traceback (most recent call last):
        ...
        ValueError: resume= replays steps stored without distillation targets and this config has algo.group_fit_coeff=1.0: resume with the run's algo.group_fit_coeff (0 or > 0)
    """  # noqa: E501 - a doctest's expected output is one line
    saved_on = float(saved.get("group_fit_coeff", 0.0)) > 0
    coeff = float(algo.group_fit_coeff)
    if saved_on != (coeff > 0):
        stored = "with" if saved_on else "without"
        raise ValueError(
            f"resume={source} replays steps stored {stored} distillation targets and this "
            f"config has algo.group_fit_coeff={coeff}: resume with the run's algo.group_fit_coeff "
            "(0 or > 0)"
        )
    # A checkpoint of grpo_branch from before the key fitted by regression.
    saved_loss = str(saved.get("group_fit_loss", "regression"))
    loss = str(algo.get("group_fit_loss", "regression"))
    if saved_on and saved_loss != loss:
        raise ValueError(
            f"resume={source} replays steps stored with algo.group_fit_loss={saved_loss} "
            f"targets and this config has algo.group_fit_loss={loss}: resume with the run's "
            "algo.group_fit_loss"
        )


def make_group_fit_loss(algo: DictConfig, policy: nn.Module) -> LossModule | None:
    """The loss of ``algo.distill_*`` beside the surrogate, or ``None`` (``group_fit_coeff=0``).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor
        >>> actor = make_discrete_actor(KinematicsMLP(5, 5, out_features=5), 5)
        >>> algo = OmegaConf.create({"group_fit_coeff": 1.0, "group_fit_temperature": 0.1,
        ...                          "group_fit_loss": "regression"})
        >>> type(make_group_fit_loss(algo, actor)).__name__
        'AdvantageRegressionLoss'
    """
    coeff = float(algo.group_fit_coeff)
    if coeff == 0:
        return None
    loss = str(algo.group_fit_loss)
    fit = GROUP_FITS.get(loss)
    if fit is None:
        raise _unknown("algo.group_fit_loss", loss, sorted(GROUP_FITS))
    return fit.make_loss(policy, coeff, float(algo.group_fit_temperature))
