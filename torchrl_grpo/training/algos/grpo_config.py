"""GRPO's config: the keys a user tunes, and the values each variant fixes for the rest.

:class:`GRPOConfig` is the ``algo`` schema of ``grpo_branch`` and ``grpo_episode``;
:data:`FIXED_SETTINGS` holds the settings that are not keys (the recommended recipe's
values), which :meth:`~torchrl_grpo.training.GRPO.fixed_settings` hands the trainer.
The experimental ``algo=grpo_lab`` (``torchrl_grpo.experimental``) makes them keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from omegaconf import MISSING

from torchrl_grpo.training.algos.base import AlgoConfig
from torchrl_grpo.training.choices import choice_enum
from torchrl_grpo.training.model_builder import BasePolicyName
from torchrl_grpo.training.retired_keys import OLD_DEFAULTS

__all__ = [
    "FIXED_SETTINGS",
    "GRPOConfig",
    "GRPOName",
    "GRPOVariant",
    "GroupFitName",
    "TailPolicyName",
]


#: The GRPO variants (``algo.name``).
GRPOVariant = Literal["grpo_branch", "grpo_episode"]
#: Who acts on greedy-tail branches after their explored steps (``algo.tail_policy``):
#: the learner, or a scripted base policy whose ``Q(s, a)`` the groups then score.
TailPolicy = Literal["learner", BasePolicyName]
#: What the group fit fits (``algo.group_fit_loss``): each action's advantage by the
#: policy's centred logits, or the policy's expected regret at each root
#: (:data:`~torchrl_grpo.training.algos.enumerated.GROUP_FITS`).
GroupFit = Literal["regression", "regret"]


def _choices(name: str, choices: Any, doc: str) -> Any:
    return choice_enum(name, choices, doc, module=__name__)


GRPOName = _choices("GRPOName", GRPOVariant, "The GRPO variant.")
TailPolicyName = _choices("TailPolicyName", TailPolicy, "Who acts on greedy-tail branches.")
GroupFitName = _choices("GroupFitName", GroupFit, "What the group fit fits.")


@dataclass
class GRPOConfig(AlgoConfig):
    """GRPO (``grpo_branch``, ``grpo_episode``): group-relative advantage, no critic.

    The keys a user tunes. Everything else of the algorithm is fixed per variant by
    :meth:`GRPO.fixed_settings` (the recommended recipe's values); the experimental
    ``algo=grpo_lab`` makes those keys too.

    Example:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.structured(GRPOConfig(name="grpo_branch", group_size=4))
        >>> print(cfg.group_size, cfg.clip_epsilon_low, cfg.clip_epsilon_high)
        4 0.2 0.28
        >>> FIXED_SETTINGS["grpo_branch"]["algo"]["first_action"]
        'enumerate'
    """

    name: GRPOName = MISSING
    group_size: int = 8
    clip_epsilon_low: float = 0.2
    clip_epsilon_high: float = 0.28
    kl_to_ref_coeff: float | None = 0.01
    tail_policy: TailPolicyName = TailPolicyName["learner"]
    tail_learner_steps: int = 0
    replay_groups: int | None = None
    group_fit_loss: GroupFitName = GroupFitName["regression"]


# The values each variant runs with for the settings GRPOConfig does not make keys:
# grpo_episode keeps the defaults the schema had; grpo_branch's are the recommended
# recipe's (conf/algo/grpo_branch.yaml before #40).
FIXED_SETTINGS: dict[str, dict[str, dict[str, Any]]] = {
    "grpo_branch": {
        "algo": {
            **OLD_DEFAULTS["algo"],
            "scale_rewards": "none",
            "explore_steps": 1,
            "first_action": "enumerate",
            "action_weights": "policy",
            "group_fit_coeff": 1.0,
            "group_fit_temperature": 1.0,
            # A key since #42; what a config written before it ran.
            "group_fit_loss": "regression",
        },
        "rollout": {**OLD_DEFAULTS["rollout"], "live_trunks": True, "stagger_trunks": True},
    },
    "grpo_episode": {
        # No enumerated groups: nothing to fit.
        "algo": {**OLD_DEFAULTS["algo"], "roots": "reset", "group_fit_coeff": 0.0},
        "rollout": OLD_DEFAULTS["rollout"],
    },
}
