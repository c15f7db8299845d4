"""Policy networks, TorchRL actor/critic builders and scripted highway policies."""

from torchrl_grpo.modules.actors import make_discrete_actor, make_value_net
from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.modules.ensemble import PolicyEnsemble
from torchrl_grpo.modules.greedy_tail import GreedyTail
from torchrl_grpo.modules.kinematics_table import KinematicsLayout
from torchrl_grpo.modules.networks import EgoAttentionNet, KinematicsMLP
from torchrl_grpo.modules.scene_features import SceneMLP
from torchrl_grpo.modules.scripted.actions import (
    META_ACTIONS,
    ConstantActionPolicy,
    RandomPolicy,
    ScriptedPolicy,
)
from torchrl_grpo.modules.scripted.policies import RulePolicy
from torchrl_grpo.modules.scripted.policy_registry import SCRIPTED_POLICIES, make_scripted_policy
from torchrl_grpo.modules.scripted.scene import Driver, Scene
from torchrl_grpo.modules.vehicle_transformer import VehicleTransformer

__all__ = [
    "META_ACTIONS",
    "SCRIPTED_POLICIES",
    "ConstantActionPolicy",
    "CrashHead",
    "Driver",
    "EgoAttentionNet",
    "GreedyTail",
    "KinematicsLayout",
    "KinematicsMLP",
    "PolicyEnsemble",
    "RandomPolicy",
    "RulePolicy",
    "Scene",
    "SceneMLP",
    "VehicleTransformer",
    "ScriptedPolicy",
    "make_discrete_actor",
    "make_scripted_policy",
    "make_value_net",
]
