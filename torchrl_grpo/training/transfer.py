"""The transfer gap: the same starting worlds driven on highway-env and on the tensor simulator.

Training on :class:`~torchrl_grpo.envs.TensorHighwayEnv` is worth what its policy does on
highway-env itself. The gap is measured paired: episode ``i`` of an evaluation starts
from ``env.set_seed(seed + i)`` on highway-env; the same world, imported through the
bridge (:meth:`~torchrl_grpo.envs.TensorHighwayEnv.state_from_highway`), is driven by the
same greedy policy on the tensor simulator, all episodes as rows of one batched rollout.
The gap is the mean per-episode difference (highway-env minus tensor), with its standard
error, of the return and of the crash indicator.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_grpo.branching.batched_search import highway_starts
from torchrl_grpo.envs.highway.tensor_env import TensorHighwayEnv
from torchrl_grpo.modules.actors import DeterministicActor
from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.results import EvalResult

__all__ = ["evaluate_on_tensor", "paired_gap", "tensor_episodes"]


@torch.no_grad()
def evaluate_on_tensor(
    env_cfg: DictConfig,
    policy: Callable[[TensorDictBase], TensorDictBase],
    *,
    episodes: int,
    seed: int,
    name: str = "policy (tensor simulator)",
    return_state: bool = False,
    dtype: torch.dtype = torch.float32,
) -> EvalResult:
    """The episodes of :func:`~torchrl_grpo.training.evaluate`, on the tensor simulator.

    Args:
        env_cfg: the ``env`` config group (a scenario and config the tensor simulator covers).
        policy: the policy; learned actors act greedily.
        episodes: how many episodes; episode ``i`` starts where highway-env's episode
            from seed ``seed + i`` starts.
        seed: the first episode's seed.
        name: the label of the result.
        return_state: write each step's simulator state into the policy's input (for a
            policy that plans from it, :class:`~torchrl_grpo.branching.LookaheadPolicy`).
        dtype: the simulator's float dtype; training's float32 by default, float64 to
            tell the simulator's agreement with highway-env from float32 rounding.

    Raises:
        ValueError: a scenario or config the tensor simulator does not cover.

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> from torchrl_grpo.training import evaluate, make_env
        >>> cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {},
        ...                         "max_episode_steps": 5})
        >>> slower = ConstantActionPolicy("SLOWER")
        >>> tensor = evaluate_on_tensor(cfg, slower, episodes=2, seed=0)
        >>> highway, _ = evaluate(make_env(cfg), slower, episodes=2, seed=0, max_steps=5)
        >>> round(paired_gap(highway, tensor)["return_gap"], 6)  # float32 rewards
        0.0
    """
    data, before = tensor_episodes(
        env_cfg, policy, episodes=episodes, seed=seed, return_state=return_state, dtype=dtype
    )
    reward = torch.where(before, data.get(("next", "reward")).reshape(episodes, -1), 0.0)
    crashed = (data.get(("next", "crashed")).reshape(episodes, -1) & before).any(1)
    speed = data.get(("next", "speed")).reshape(episodes, -1).double()
    lengths = before.sum(1)
    return EvalResult(
        name,
        returns=reward.double().sum(1).tolist(),
        crashed=crashed.tolist(),
        lengths=lengths.tolist(),
        speeds=((speed * before).sum(1) / lengths.clamp(min=1)).tolist(),
        seeds=list(range(seed, seed + episodes)),
    )


@torch.no_grad()
def tensor_episodes(
    env_cfg: DictConfig,
    policy: Callable[[TensorDictBase], TensorDictBase],
    *,
    episodes: int,
    seed: int,
    return_state: bool = False,
    dtype: torch.dtype = torch.float32,
) -> tuple[TensorDictBase, torch.Tensor]:
    """The greedy rollout behind :func:`evaluate_on_tensor`, step by step.

    Returns:
        The ``[episodes, T]`` rollout and the ``[episodes, T]`` mask of the steps that
        belong to each episode (up to its first done).

    Example:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_grpo.modules import ConstantActionPolicy
        >>> cfg = OmegaConf.create({"scenario": "highway-fast-v0", "config": {},
        ...                         "max_episode_steps": 4})
        >>> data, steps = tensor_episodes(cfg, ConstantActionPolicy("IDLE"), episodes=2, seed=0)
        >>> data.batch_size, steps.shape
        (torch.Size([2, 4]), torch.Size([2, 4]))
    """
    max_steps = int(env_cfg.get("max_episode_steps", 1000))
    # Seeded: an env drawn without a seed takes one from torch's generator, and an
    # evaluation must not move the training's random stream.
    env = TensorHighwayEnv(
        str(env_cfg.scenario),
        env_overrides(env_cfg),
        num_envs=episodes,
        seed=seed,
        return_state=return_state,
        dtype=dtype,
    )
    td = highway_starts(env, range(seed, seed + episodes))
    if isinstance(policy, TensorDictModuleBase) and hasattr(policy, "get_dist"):
        policy = DeterministicActor(policy)
        if dtype != torch.float32:
            policy = _Float32Observation(policy)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        data = env.rollout(
            max_steps, policy, tensordict=td, auto_reset=False, break_when_any_done=False
        )
    done = data.get(("next", "done")).reshape(episodes, -1)
    # A row counts up to its first done; later steps belong to no episode.
    before = torch.cumsum(done.long(), 1) - done.long() == 0
    return data, before


class _Float32Observation(TensorDictModuleBase):
    """A learned policy fed float32 observations, as highway-env's wrapper gives them.

    In a float64 simulator the observation is float64, and a float32 network refuses it.
    """

    def __init__(self, policy: TensorDictModuleBase) -> None:
        super().__init__()
        self.policy = policy
        self.in_keys, self.out_keys = list(policy.in_keys), list(policy.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:  # noqa: D102
        seen = tensordict.clone(False).set("observation", tensordict["observation"].float())
        return tensordict.update(self.policy(seen).exclude("observation"))


def paired_gap(highway: EvalResult, tensor: EvalResult) -> dict[str, float]:
    """highway-env minus tensor simulator, episode by episode: return and crash rate.

    Returns:
        ``return_gap`` and ``crash_gap`` (means of the paired differences),
        ``return_gap_sem`` (their standard error), ``tensor_return`` and
        ``tensor_crash_rate``.

    Raises:
        ValueError: the results are not of the same seeds.

    Example:
        >>> a = EvalResult("a", [20.0, 22.0], [False, True], [30, 12], [20.0, 21.0], [0, 1])
        >>> b = EvalResult("b", [21.0, 22.0], [False, False], [30, 30], [20.0, 21.0], [0, 1])
        >>> gap = paired_gap(a, b)
        >>> gap["return_gap"], gap["crash_gap"], gap["return_gap_sem"]
        (-0.5, 0.5, 0.5)
    """
    if highway.seeds != tensor.seeds:
        raise ValueError(
            f"a paired gap needs the same episodes: seeds {highway.seeds} vs {tensor.seeds}"
        )
    diff = torch.tensor(highway.returns, dtype=torch.float64) - torch.tensor(
        tensor.returns, dtype=torch.float64
    )
    n = diff.numel()
    sem = float(diff.std() / math.sqrt(n)) if n > 1 else 0.0
    crash = torch.tensor(highway.crashed, dtype=torch.float64) - torch.tensor(
        tensor.crashed, dtype=torch.float64
    )
    summary = tensor.summary()
    return {
        "return_gap": float(diff.mean()),
        "return_gap_sem": sem,
        "crash_gap": float(crash.mean()),
        "tensor_return": summary["return"],
        "tensor_crash_rate": summary["crash_rate"],
    }
