"""What differs between the scenarios of TensorHighwayEnv: step, outputs, fresh worlds, bridge.

The env class (:mod:`.tensor_env`) is one TorchRL env for every scenario of the
simulator; a :class:`TensorModel` holds the scenario's pure functions and its bridge:

* highway-v0 / highway-fast-v0 draw fresh worlds from the simulator's own per-world
  streams (:mod:`torchrl_grpo.sim.rng`) and give highway-env generator words drawn
  from them;
* merge-v0, roundabout-v0 and intersection-v0 draw fresh worlds from highway-env's
  generator itself, carried in the state's ``highway.rng`` words, on the host
  (:func:`~.merge_bridge.merge_draws`): row
  ``i`` of an env seeded with ``s`` replays ``HighwayEnv(scenario)``'s episodes
  after ``reset(seed=s + i)``.

Example:
    >>> model = tensor_model("merge-v0")
    >>> model.components[-1], model.draws_from_words
    ('merging_speed_reward', True)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from tensordict import TensorDict

from torchrl_grpo.envs.core.gym_state import seeded_rng_words
from torchrl_grpo.envs.highway.bridge import HighwayBridge
from torchrl_grpo.envs.highway.intersection_bridge import (
    HOST_DRAWS,
    IntersectionBridge,
    IntersectionDraws,
    intersection_fresh,
)
from torchrl_grpo.envs.highway.merge_bridge import MergeBridge, merge_draws
from torchrl_grpo.envs.highway.roundabout_bridge import RoundaboutBridge, roundabout_draws
from torchrl_grpo.envs.highway.tensor_state import fresh_highway_words
from torchrl_grpo.sim.intersection import (
    INTERSECTION_ACTIONS,
    FramesFn,
    intersection_step,
    tensor_frames,
)
from torchrl_grpo.sim.intersection_output import (
    INTERSECTION_REWARD_COMPONENTS,
    observe_intersection,
)
from torchrl_grpo.sim.merge import merge_step
from torchrl_grpo.sim.merge_output import MERGE_REWARD_COMPONENTS, observe_merge
from torchrl_grpo.sim.merge_reset import reset_merge
from torchrl_grpo.sim.reset import reset_world
from torchrl_grpo.sim.reward import REWARD_COMPONENTS
from torchrl_grpo.sim.roundabout import roundabout_step
from torchrl_grpo.sim.roundabout_output import ROUNDABOUT_REWARD_COMPONENTS, observe_roundabout
from torchrl_grpo.sim.roundabout_reset import reset_roundabout
from torchrl_grpo.sim.simulate import observe_world, step
from torchrl_grpo.sim.state import World

__all__ = ["TensorModel", "output_tensordict", "tensor_model", "zero_fresh_rewards"]


class TensorModel(NamedTuple):
    """A scenario's functions, as the env calls them.

    Attributes:
        components: the reward components' names, in HighwayEnv's order.
        step: ``(world, action, params, dense=...) -> (world, outputs)``.
        observe: ``(world, params) -> outputs``.
        fresh: ``(world, rows, words, seeds, params) -> (world, words, seeds)``: fresh
            worlds on ``rows`` and the highway-env generator words and seeds after.
        seed_words: ``(count, seed) -> (words, seeds)`` of freshly seeded rows, or
            ``None`` where the words are drawn at reset.
        bridge: the bridge class.
        draws_from_words: fresh worlds come from the words (not the sim's streams).
        compiles: the step has compiled stages (``TensorHighwayEnv.compile``).
        actions: the number of discrete actions.
        spawns: the step draws from highway-env's generator: ``step(world, action,
            words) -> (world, outputs, words)`` (intersection-v0's spawns).

    Example:
        >>> tensor_model("merge-v0").bridge.__name__
        'MergeBridge'
    """

    components: tuple[str, ...]
    step: Callable
    observe: Callable
    fresh: Callable
    seed_words: Callable | None
    bridge: type
    draws_from_words: bool
    compiles: bool
    actions: int = 5
    spawns: bool = False


def _highway_fresh(world: World, rows, words, seeds, params):
    world, new = fresh_highway_words(reset_world(world, rows, params), rows)
    words = torch.where(rows.unsqueeze(-1), new, words)
    return world, words, torch.where(rows, -1, seeds)


def _merge_fresh(world: World, rows, words, seeds, params, replay=merge_draws):
    # replay: numpy's (merge_draws) or the C++ step's (native_merge_draws), the same bits.
    draws, words = replay(words, rows)
    return reset_merge(world, rows, draws, params), words, seeds


def _roundabout_fresh(world: World, rows, words, seeds, params, replay=roundabout_draws):
    # replay: numpy's (roundabout_draws) or the C++ step's (native_roundabout_draws).
    draws, words = replay(words, rows, params)
    return reset_roundabout(world, rows, draws, params), words, seeds


def _roundabout_step(world, action, params, dense=False, stages=None):
    del dense, stages
    return roundabout_step(world, action, params)


def _intersection_step(
    world,
    action,
    words,
    params,
    dense=False,
    stages=None,
    frames: FramesFn = tensor_frames,
    draws: IntersectionDraws = HOST_DRAWS,
):
    # frames and draws: the tensor path's, or the C++ ones (step_modes.native_mode).
    del dense, stages
    rows = torch.ones_like(world.steps, dtype=torch.bool)
    probability = params.traffic.spawn_probability
    drawn, dropped, kept = draws.spawn(words, rows, params, probability)
    world, out, stayed = intersection_step(world, action, drawn, params, frames)
    return world, out, torch.where(stayed.unsqueeze(-1), kept, dropped)


def _merge_seed_words(count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    seeds = torch.arange(count, dtype=torch.int64) + seed
    return torch.stack([seeded_rng_words(int(s)) for s in seeds]), seeds


def _merge_step(world, action, params, dense=False, stages=None):
    # One path: MOBIL and the collisions compact with host reads (a GPU syncs there).
    del dense, stages
    return merge_step(world, action, params)


def tensor_model(scenario: str) -> TensorModel:
    """The :class:`TensorModel` of a scenario of ``TENSOR_SCENARIOS``.

    Example:
        >>> tensor_model("highway-fast-v0").compiles
        True
    """
    if scenario == "intersection-v0":
        return TensorModel(
            components=INTERSECTION_REWARD_COMPONENTS,
            step=_intersection_step,
            observe=observe_intersection,
            fresh=intersection_fresh,
            seed_words=_merge_seed_words,
            bridge=IntersectionBridge,
            draws_from_words=True,
            compiles=False,
            actions=len(INTERSECTION_ACTIONS),
            spawns=True,
        )
    if scenario == "roundabout-v0":
        return TensorModel(
            components=ROUNDABOUT_REWARD_COMPONENTS,
            step=_roundabout_step,
            observe=observe_roundabout,
            fresh=_roundabout_fresh,
            seed_words=_merge_seed_words,
            bridge=RoundaboutBridge,
            draws_from_words=True,
            compiles=False,
        )
    if scenario == "merge-v0":
        return TensorModel(
            components=MERGE_REWARD_COMPONENTS,
            step=_merge_step,
            observe=observe_merge,
            fresh=_merge_fresh,
            seed_words=_merge_seed_words,
            bridge=MergeBridge,
            draws_from_words=True,
            compiles=False,
        )
    return TensorModel(
        components=REWARD_COMPONENTS,
        step=step,
        observe=observe_world,
        fresh=_highway_fresh,
        seed_words=None,
        bridge=HighwayBridge,
        draws_from_words=False,
        compiles=True,
    )


def output_tensordict(
    outputs: dict, batch: torch.Size, dtype: torch.dtype, device: torch.device
) -> TensorDict:
    """A step's outputs as the env's TensorDict ``[B]``: columns ``[B, 1]``, floats in ``dtype``.

    Example:
        >>> import torch
        >>> from torchrl_grpo.envs import tensor_params
        >>> from torchrl_grpo.sim import empty_world, observe_world
        >>> params = tensor_params("highway-fast-v0")
        >>> out = observe_world(empty_world(2, params.num_vehicles), params)
        >>> output_tensordict(out, torch.Size([2]), torch.float64, "cpu")["speed"].shape
        torch.Size([2, 1])
    """

    def column(t: torch.Tensor) -> torch.Tensor:
        return t.to(dtype).unsqueeze(-1)

    return TensorDict(
        {
            "observation": outputs["observation"].to(dtype),
            "crashed": outputs["crashed"].unsqueeze(-1),
            "on_road": outputs["on_road"].unsqueeze(-1),
            "speed": column(outputs["speed"]),
            "ego_position": outputs["ego_position"].to(dtype),
            "ego_heading": column(outputs["ego_heading"]),
            "reward_components": {k: column(v) for k, v in outputs["reward_components"].items()},
        },
        batch_size=batch,
        device=device,
    )


def zero_fresh_rewards(out: TensorDict, steps: torch.Tensor, components: tuple[str, ...]) -> None:
    """Zero the reward components of fresh episodes (``steps == 0``) in ``out``, in place.

    As HighwayEnv reports them: no action was taken yet in a fresh episode.

    Example:
        >>> out = TensorDict({("reward_components", "a"): torch.ones(2, 1)}, batch_size=[2])
        >>> zero_fresh_rewards(out, torch.tensor([0, 3]), ("a",))
        >>> out["reward_components", "a"].flatten().tolist()
        [0.0, 1.0]
    """
    fresh = (steps == 0).unsqueeze(-1)
    for name in components:
        part = out.get(("reward_components", name))
        out.set(("reward_components", name), torch.where(fresh, torch.zeros_like(part), part))
