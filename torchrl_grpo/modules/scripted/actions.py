"""highway-env's meta actions, the scripted-policy wrapper and the scene-blind policies.

:class:`ScriptedPolicy` is what every scripted policy is: a
:class:`~tensordict.nn.TensorDictModule` around a decision module ``observation ->
action``. :class:`ConstantActionPolicy` and :class:`RandomPolicy` ignore the scene; the
driving policies that read it are in :mod:`~torchrl_grpo.modules.scripted.policies`.
"""

from __future__ import annotations

from typing import Literal

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

__all__ = [
    "FASTER",
    "IDLE",
    "LANE_LEFT",
    "LANE_RIGHT",
    "LONGITUDINAL_ACTIONS",
    "META_ACTIONS",
    "SLOWER",
    "ConstantActionPolicy",
    "MetaAction",
    "RandomPolicy",
    "ScriptedPolicy",
]

# Indices of highway-env's DiscreteMetaAction.ACTIONS_ALL (envs/common/action.py).
LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = 0, 1, 2, 3, 4
MetaAction = Literal["LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER"]
#: highway-env's DiscreteMetaAction by name: the action index a policy writes, e.g.
#: ``META_ACTIONS["SLOWER"] == 4``.
META_ACTIONS: dict[str, int] = {
    "LANE_LEFT": LANE_LEFT,
    "IDLE": IDLE,
    "LANE_RIGHT": LANE_RIGHT,
    "FASTER": FASTER,
    "SLOWER": SLOWER,
}


#: The constant policies of a longitudinal-only DiscreteMetaAction (intersection-v0's
#: ``lateral=False``: 0 SLOWER, 1 IDLE, 2 FASTER), by scripted-policy name.
LONGITUDINAL_ACTIONS: dict[str, int] = {"slower": 0, "idle": 1, "faster": 2}


class ScriptedPolicy(TensorDictModule):
    """A :class:`TensorDictModule` around a decision module ``observation -> action``.

    Args:
        decider: module mapping ``[*batch, V, F]`` to int64 actions ``[*batch]``.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from torchrl_grpo.envs import HighwayEnv
        >>> class AlwaysFaster(nn.Module):
        ...     def forward(self, observation):
        ...         return torch.full(observation.shape[:-2], FASTER, dtype=torch.int64)
        >>> policy = ScriptedPolicy(AlwaysFaster())
        >>> HighwayEnv("merge-v0", seed=0).rollout(3, policy)["action"].tolist()
        [3, 3, 3]
    """

    def __init__(
        self, decider: nn.Module, in_key: NestedKey = "observation", out_key: NestedKey = "action"
    ) -> None:
        super().__init__(decider, in_keys=[in_key], out_keys=[out_key])


class _Constant(nn.Module):
    def __init__(self, action: int) -> None:
        super().__init__()
        self.action = action

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.full(
            observation.shape[:-2], self.action, dtype=torch.int64, device=observation.device
        )


class ConstantActionPolicy(ScriptedPolicy):
    """Always plays the same action.

    Args:
        action: an action index or a DiscreteMetaAction name.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> policy = ConstantActionPolicy("SLOWER")
        >>> from tensordict import TensorDict
        >>> policy(TensorDict(observation=torch.zeros(2, 3, 5, 5), batch_size=[2, 3]))[
        ...     "action"].unique().tolist()
        [4]
    """

    def __init__(
        self,
        action: int | MetaAction,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        if isinstance(action, str):
            if action not in META_ACTIONS:
                raise ValueError(
                    f"Unknown action {action!r}; expected one of {list(META_ACTIONS)}."
                )
            action = META_ACTIONS[action]
        super().__init__(_Constant(int(action)), in_key, out_key)


class _Random(nn.Module):
    def __init__(self, n_actions: int, seed: int | None) -> None:
        super().__init__()
        self.n_actions = n_actions
        self.generator = torch.Generator()
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(seed)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        # Draw on the CPU generator, then move: the sequence is the same on any device.
        action = torch.randint(
            self.n_actions, observation.shape[:-2], generator=self.generator, dtype=torch.int64
        )
        return action.to(observation.device)


class RandomPolicy(ScriptedPolicy):
    """Uniformly random actions from its own seeded generator.

    Args:
        n_actions: number of discrete actions.
        seed: seed of the policy's :class:`torch.Generator`; ``None`` seeds it from
            the OS. A copy (deepcopy, pickle, e.g. one per collector worker) carries
            the generator state and so repeats the same draws: seed each copy.
        in_key: observation key.
        out_key: action key.

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict(observation=torch.zeros(8, 5, 5), batch_size=[8])
        >>> a = RandomPolicy(5, seed=0)(td.clone())["action"]
        >>> b = RandomPolicy(5, seed=0)(td.clone())["action"]
        >>> bool((a == b).all()), bool(((a >= 0) & (a < 5)).all())
        (True, True)
    """

    def __init__(
        self,
        n_actions: int = 5,
        seed: int | None = None,
        in_key: NestedKey = "observation",
        out_key: NestedKey = "action",
    ) -> None:
        super().__init__(_Random(n_actions, seed), in_key, out_key)
