"""Policy networks, TorchRL actor/critic builders and scripted highway policies."""

from torchrl_grpo.modules.actors import (
    ContinuousDistribution,
    DeterministicActor,
    make_continuous_actor,
    make_discrete_actor,
    make_value_net,
)
from torchrl_grpo.modules.crash_head import CrashHead
from torchrl_grpo.modules.ensemble import PolicyEnsemble, member_halves
from torchrl_grpo.modules.greedy_tail import EXPLORED, GreedyTail
from torchrl_grpo.modules.kinematics import (
    DEFAULT_FEATURES,
    LANE_WIDTH,
    MAX_SPEED,
    VEHICLE_LENGTH,
    KinematicsLayout,
)
from torchrl_grpo.modules.neighbours import NeighbourFeatures, NeighbourMLP
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
    Driver,
    LaneChangePolicy,
    MetaAction,
    RandomPolicy,
    RulePolicy,
    Scene,
    ScriptedPolicy,
    make_scripted_policy,
    time_to_collision,
)
from torchrl_grpo.modules.sharing import shared_forward, shared_networks

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
    "CrashHead",
    "DeterministicActor",
    "Driver",
    "EgoAttentionNet",
    "GreedyTail",
    "KinematicsLayout",
    "KinematicsMLP",
    "LaneChangePolicy",
    "MetaAction",
    "NeighbourFeatures",
    "NeighbourMLP",
    "NetworkKind",
    "PolicyEnsemble",
    "PriorLogits",
    "RandomPolicy",
    "RulePolicy",
    "Scene",
    "SceneFeatures",
    "SceneMLP",
    "ScriptedPolicy",
    "make_continuous_actor",
    "make_discrete_actor",
    "make_network",
    "make_scripted_policy",
    "make_value_net",
    "member_halves",
    "shared_forward",
    "shared_networks",
    "time_to_collision",
]
