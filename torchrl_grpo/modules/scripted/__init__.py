"""Hand-written policies for highway-env's DiscreteMetaAction on Kinematics observations.

Every policy is a :class:`~tensordict.nn.TensorDictModule` reading ``"observation"``
(``[*batch, V, F]``) and writing an int64 ``"action"`` (``[*batch]``), so it plugs into
``env.rollout``, collectors and group rollouts like a learned actor. The policies keep
no state between calls: their decision depends on the current observation only, which
keeps them exact under snapshot branching.

- :mod:`~torchrl_grpo.modules.scripted.actions`: the meta actions, the
  :class:`ScriptedPolicy` wrapper, constant and random policies;
- :mod:`~torchrl_grpo.modules.scripted.scene`: the :class:`Scene` a driver reads from
  the observation, and the :class:`Driver` base class;
- :mod:`~torchrl_grpo.modules.scripted.drivers`: the decisions of the driving policies;
- :mod:`~torchrl_grpo.modules.scripted.policies`: the driving policies;
- :mod:`~torchrl_grpo.modules.scripted.registry`: the policies by name.
"""

from torchrl_grpo.modules.scripted.actions import (
    FASTER,
    IDLE,
    LANE_LEFT,
    LANE_RIGHT,
    META_ACTIONS,
    SLOWER,
    ConstantActionPolicy,
    MetaAction,
    RandomPolicy,
    ScriptedPolicy,
)
from torchrl_grpo.modules.scripted.policies import (
    AggressivePolicy,
    CautiousPolicy,
    ConservativePolicy,
    LaneChangePolicy,
    RulePolicy,
)
from torchrl_grpo.modules.scripted.registry import SCRIPTED_POLICIES, make_scripted_policy
from torchrl_grpo.modules.scripted.scene import Driver, Scene, time_to_collision

__all__ = [
    "FASTER",
    "IDLE",
    "LANE_LEFT",
    "LANE_RIGHT",
    "META_ACTIONS",
    "SCRIPTED_POLICIES",
    "SLOWER",
    "AggressivePolicy",
    "CautiousPolicy",
    "ConservativePolicy",
    "ConstantActionPolicy",
    "Driver",
    "LaneChangePolicy",
    "MetaAction",
    "RandomPolicy",
    "RulePolicy",
    "Scene",
    "ScriptedPolicy",
    "make_scripted_policy",
    "time_to_collision",
]
