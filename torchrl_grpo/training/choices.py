"""The string choices of the config schemas: enums built from the library's ``Literal`` types.

OmegaConf rejects ``typing.Literal`` fields and validates an ``Enum`` field by member
*name*. :func:`choice_enum` turns a ``Literal`` into a ``StrEnum`` whose member names
are the ``Literal``'s values, so that what a user types on the command line, the
member's value and what ``str()`` prints are one string, and the choices are written
once, where the library defines them. Names need not be identifiers: the choice
``"continue"`` (a Python keyword) is the member ``RootKindName["continue"]``. An
alias is one more name of a member, so that an older spelling still validates and
reads as the current one.

The enums of the choices the library defines are here; an algorithm's own choices
are built in its file of :mod:`~torchrl_grpo.training.algos`.
"""

from __future__ import annotations

import typing
from collections.abc import Mapping
from enum import StrEnum
from typing import Any

from torchrl_grpo.branching.continuation import Selection
from torchrl_grpo.branching.group_collector import RootKind
from torchrl_grpo.modules.greedy_tail import FirstAction
from torchrl_grpo.objectives.advantage import Baseline, Returns, RewardScaling
from torchrl_grpo.objectives.bootstrap import BootstrapMode
from torchrl_grpo.objectives.grpo_loss import Aggregation
from torchrl_grpo.objectives.kl import KLEstimator
from torchrl_grpo.objectives.survival import CrashLabel
from torchrl_grpo.training.env_builder import EnvBackend, RolloutBackend
from torchrl_grpo.training.logging_builder import LoggerKind
from torchrl_grpo.training.model_builder import ModelArchitecture

__all__ = [
    "AggregationName",
    "Backend",
    "BaselineName",
    "BootstrapName",
    "CrashLabelName",
    "EnvBackendName",
    "FirstActionName",
    "KLEstimatorName",
    "LoggerBackend",
    "ModelKind",
    "ReturnsName",
    "RootKindName",
    "ScaleRewards",
    "SelectionName",
    "choice_enum",
]


def choice_enum(
    name: str,
    choices: Any,
    doc: str,
    *,
    module: str,
    aliases: Mapping[str, str] | None = None,
) -> type[StrEnum]:
    """A ``StrEnum`` with one member per value of the ``Literal`` ``choices``.

    Args:
        name: the enum's name (as the module binds it, so that it pickles).
        choices: a ``Literal`` type; nested ``Literal`` types are flattened.
        doc: the enum's docstring (the config reference shows its first paragraph).
        module: the module that binds the enum (``__name__``).
        aliases: ``{old spelling: choice}``: extra names of existing members.

    Raises:
        ValueError: ``choices`` is not a ``Literal`` of strings, or an alias names no
            choice.

    Example:
        >>> from typing import Literal
        >>> Kind = Literal["reset", "trunk", "continue"]
        >>> Roots = choice_enum("Roots", Kind, "Where groups start.", module=__name__,
        ...                     aliases={"continuation": "continue"})
        >>> [str(member) for member in Roots]
        ['reset', 'trunk', 'continue']
        >>> Roots["continuation"] is Roots["continue"], Roots["trunk"] == "trunk"
        (True, True)
    """
    values = typing.get_args(choices)
    if typing.get_origin(choices) is not typing.Literal or not all(
        isinstance(value, str) for value in values
    ):
        raise ValueError(f"{name}: choices must be a Literal of strings, got {choices!r}")
    aliases = dict(aliases or {})
    unknown = {alias: target for alias, target in aliases.items() if target not in values}
    if unknown:
        raise ValueError(f"{name}: aliases {unknown} name no choice of {values}")
    # A name bound to an existing value becomes an alias of that member (Enum semantics).
    members = [(value, value) for value in values] + list(aliases.items())
    enum_type = StrEnum(name, members, module=module)
    enum_type.__doc__ = doc
    return enum_type


def _choices(name: str, choices: Any, doc: str, **aliases: str) -> Any:
    return choice_enum(name, choices, doc, module=__name__, aliases=aliases)


# ``roots: continue`` was spelt ``continuation`` before the choice came from the
# library's RootKind: configs, and checkpoints, that say so still validate.
RootKindName = _choices(
    "RootKindName",
    RootKind,
    "Where GRPO groups start (see :class:`~torchrl_grpo.branching.GroupCollector`).",
    continuation="continue",
)
SelectionName = _choices("SelectionName", Selection, "Branch selection of ``roots=continue``.")
AggregationName = _choices(
    "AggregationName",
    Aggregation,
    "How :class:`~torchrl_grpo.objectives.GRPOLoss` averages over steps.",
)
KLEstimatorName = _choices("KLEstimatorName", KLEstimator, "KL estimator of the reference term.")
ReturnsName = _choices(
    "ReturnsName", Returns, "Per-branch (outcome) or per-step (reward-to-go) group returns."
)
BaselineName = _choices(
    "BaselineName", Baseline, "Group baseline: mean (GRPO) or leave-one-out (RLOO)."
)
ScaleRewards = _choices(
    "ScaleRewards", RewardScaling, "Division of the centred returns (TRL's ``scale_rewards``)."
)
BootstrapName = _choices(
    "BootstrapName", BootstrapMode, "Value credited to a GRPO branch cut by the horizon."
)
CrashLabelName = _choices(
    "CrashLabelName", CrashLabel, "What a crash head learns of a branch (``algo.crash_label``)."
)
FirstActionName = _choices(
    "FirstActionName",
    FirstAction,
    "How a greedy-tail branch picks its first action (``algo.first_action``).",
)
ModelKind = _choices("ModelKind", ModelArchitecture, "Network over the Kinematics table.")
Backend = _choices(
    "Backend",
    RolloutBackend,
    "How the rollout workers run (``ray``: GRPO groups on Ray actors, see ``rollout.ray``).",
)
EnvBackendName = _choices(
    "EnvBackendName",
    EnvBackend,
    "The simulator training runs on: tensor, native (its C++ step), highway, or auto "
    "(tensor where it covers the config).",
)
LoggerBackend = _choices("LoggerBackend", LoggerKind, "Where metrics go.")
