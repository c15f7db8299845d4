"""Policy networks, TorchRL actor/critic builders and scripted highway policies."""

from torchrl_grpo.modules.actors import (
    ContinuousDistribution,
    DeterministicActor,
    make_continuous_actor,
    make_discrete_actor,
    make_value_net,
)
from torchrl_grpo.modules.greedy_tail import EXPLORED, GreedyTail
from torchrl_grpo.modules.kinematics import (
    DEFAULT_FEATURES,
    LANE_WIDTH,
    MAX_SPEED,
    VEHICLE_LENGTH,
    KinematicsLayout,
)
from torchrl_grpo.modules.networks import (
    EgoAttentionNet,
    KinematicsMLP,
    NetworkKind,
    make_network,
)
from torchrl_grpo.modules.prior import PriorLogits
from torchrl_grpo.modules.scene import SceneFeatures, SceneMLP
from torchrl_grpo.modules.scripted import (
    FASTER,
    IDLE,
    LANE_LEFT,
    LANE_RIGHT,
    META_ACTIONS,
    SCRIPTED_POLICIES,
    SLOWER,
    AggressivePolicy,
    CautiousPolicy,
    ConservativePolicy,
    ConstantActionPolicy,
    LaneChangePolicy,
    MetaAction,
    RandomPolicy,
    RulePolicy,
    ScriptedPolicy,
    make_scripted_policy,
)

__all__ = [
    "DEFAULT_FEATURES",
    "EXPLORED",
    "FASTER",
    "IDLE",
    "LANE_LEFT",
    "LANE_RIGHT",
    "LANE_WIDTH",
    "MAX_SPEED",
    "META_ACTIONS",
    "SCRIPTED_POLICIES",
    "SLOWER",
    "VEHICLE_LENGTH",
    "AggressivePolicy",
    "CautiousPolicy",
    "ConservativePolicy",
    "ConstantActionPolicy",
    "ContinuousDistribution",
    "DeterministicActor",
    "EgoAttentionNet",
    "GreedyTail",
    "KinematicsLayout",
    "KinematicsMLP",
    "LaneChangePolicy",
    "MetaAction",
    "NetworkKind",
    "PriorLogits",
    "RandomPolicy",
    "RulePolicy",
    "SceneFeatures",
    "SceneMLP",
    "ScriptedPolicy",
    "make_continuous_actor",
    "make_discrete_actor",
    "make_network",
    "make_scripted_policy",
    "make_value_net",
]
