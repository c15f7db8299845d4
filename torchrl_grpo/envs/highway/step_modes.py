"""How TensorHighwayEnv advances its worlds: eagerly, through ``torch.compile``, or in C++.

Each function returns a :class:`StepMode`: the env's step, ``(world, action) -> (world,
outputs)``, its observation of worlds that did not step (after a reset) and its fresh
episodes, all pure functions of tensors:

- :func:`eager_mode`: the tensor path of :mod:`torchrl_grpo.sim`, op by op. On a CPU it
  compacts the vehicles that take a decision; on a GPU it keeps static shapes (dense),
  so that no step waits for the host.
- :func:`compiled_mode`: the same through ``torch.compile``. TorchRL's own
  ``EnvBase.compile`` compiled the whole ``step_and_maybe_reset`` around the eager
  step's data-dependent compaction and recompiled at every step. Here only pure step
  functions compile, on the first step, once per batch size: on a CPU the stages that
  compute every vehicle anyway (:class:`~torchrl_grpo.sim.simulate.Stages`: lane index
  and IDM, steering, kinematics, observation), between the eager compacted stages;
  with ``dense=True`` (the default on a GPU) the whole dense step (static shapes for
  CUDA graphs; on a CPU 12 times the eager arithmetic, slower even compiled).
- :func:`native_mode`: highway-v0 and highway-fast-v0 on a CPU with the
  substeps, the observation and the fresh episodes in C++
  (:mod:`torchrl_grpo.sim.native`), merge-v0 and roundabout-v0 with their substeps in
  C++ (:mod:`torchrl_grpo.sim.routed_native`), intersection-v0 with its frames and
  their right of way in C++ (:mod:`torchrl_grpo.sim.intersection_native`), worlds
  split over threads; the three with highway-env's reset and spawn draws replayed in
  C++ (:mod:`.native_draws`).

Compiled and C++ steps compute the eager step's model expression by expression, but
round a few functions differently (1 to 2 ulp): they replay their own bits after a
restore, and agree with the eager step within rounding, not bit for bit.

Example:
    >>> from torchrl_grpo.envs import TensorHighwayEnv
    >>> env = TensorHighwayEnv(num_envs=4, seed=0).native()  # the C++ step
    >>> env.rollout(3)["next", "observation"].shape
    torch.Size([4, 3, 5, 5])
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from torchrl_grpo.envs.highway.intersection_bridge import IntersectionDraws
from torchrl_grpo.envs.highway.native_draws import (
    native_ego_draws,
    native_merge_draws,
    native_roundabout_draws,
    native_spawn_draws,
)
from torchrl_grpo.envs.highway.tensor_models import tensor_model
from torchrl_grpo.sim.draws_native import load_draws_library
from torchrl_grpo.sim.intersection_native import native_frames, rules_of
from torchrl_grpo.sim.native import (
    load_library,
    native_fresh,
    native_observe,
    native_params,
    native_step,
)
from torchrl_grpo.sim.routed_native import load_routed_library, routed_road, routed_step
from torchrl_grpo.sim.simulate import compiled_stages, eager_stages, substep

__all__ = [
    "NATIVE_SCENARIOS",
    "ROUTED_NATIVE_SCENARIOS",
    "StepMode",
    "compiled_mode",
    "eager_mode",
    "load_native",
    "native_mode",
]

#: The scenarios whose step has a C++ version.
NATIVE_SCENARIOS = (
    "highway-v0", "highway-fast-v0", "merge-v0", "roundabout-v0", "intersection-v0",
)  # fmt: skip
#: Those of them on road graphs, whose observation and resets stay the tensor path's.
ROUTED_NATIVE_SCENARIOS = ("merge-v0", "roundabout-v0", "intersection-v0")


class StepMode(NamedTuple):
    """How the env advances and observes its worlds.

    Attributes:
        name: ``"eager"``, ``"compiled"`` or ``"native"``.
        step: ``(world, action) -> (world, outputs)``.
        observe: ``(world) -> outputs``.
        fresh: ``(world, rows, words, seeds) -> (world, words, seeds)``: new episodes in
            ``rows``, with the highway-env generator words the bridge carries.
    """

    name: str
    step: Callable
    observe: Callable
    fresh: Callable


def eager_mode(model, params, device: torch.device) -> StepMode:
    """The tensor step, dense (static shapes) on a GPU, compacted on a CPU.

    Example:
        >>> from torchrl_grpo.envs.highway.tensor_models import tensor_model
        >>> from torchrl_grpo.envs import tensor_params
        >>> mode = eager_mode(tensor_model("highway-fast-v0"), tensor_params("highway-fast-v0"),
        ...                   torch.device("cpu"))
        >>> mode.step.keywords["dense"]
        False
    """
    step = functools.partial(model.step, params=params, dense=device.type == "cuda")
    observe = functools.partial(model.observe, params=params)
    return StepMode("eager", step, observe, functools.partial(model.fresh, params=params))


def compiled_mode(
    model, params, device: torch.device, dense: bool | None = None, **kwargs: Any
) -> StepMode:
    """The step through ``torch.compile(..., **kwargs)`` (``dynamic`` defaults to ``False``).

    Args:
        model: the scenario's :class:`~torchrl_grpo.envs.highway.tensor_models.TensorModel`.
        params: its constants.
        device: where the worlds live.
        dense: compile the dense step, one substep and the observation (default: on a
            GPU only).
        **kwargs: forwarded to ``torch.compile``.

    Returns:
        The mode (the observation of fresh worlds stays eager); the eager one for
        scenarios without compiled stages.

    Example:
        >>> from torchrl_grpo.envs.highway.tensor_models import tensor_model
        >>> from torchrl_grpo.envs import tensor_params
        >>> mode = compiled_mode(tensor_model("highway-fast-v0"),
        ...                      tensor_params("highway-fast-v0"), torch.device("cpu"))
        >>> callable(mode.step)
        True
    """
    kwargs.setdefault("dynamic", False)
    eager = eager_mode(model, params, device)
    if not model.compiles:
        return eager
    if dense if dense is not None else device.type == "cuda":
        # One compiled substep called `frames` times and a compiled observation: the
        # whole step unrolls its substeps into one graph, which Inductor had not finished
        # lowering after five minutes on a CPU core (one substep: 44 s).
        eager_parts = eager_stages()
        stages = eager_parts._replace(observe=torch.compile(eager_parts.observe, **kwargs))
        frame = torch.compile(substep, **kwargs)
        step = functools.partial(model.step, params=params, dense=True, stages=stages, frame=frame)
    else:
        step = functools.partial(model.step, params=params, stages=compiled_stages(**kwargs))
    return eager._replace(name="compiled", step=step)


def native_mode(
    scenario: str, params, device: torch.device, threads: int | None = None
) -> StepMode:
    """The C++ step of a scenario of ``NATIVE_SCENARIOS`` on a CPU.

    highway-v0 and highway-fast-v0 step, observe and draw fresh worlds in C++
    (:mod:`torchrl_grpo.sim.native`); merge-v0 and roundabout-v0 step their substeps in
    C++ (:mod:`torchrl_grpo.sim.routed_native`) and keep the tensor observation and resets;
    intersection-v0 runs its frames in C++, in steps and in the reset's warm-up
    (:mod:`torchrl_grpo.sim.intersection_native`), and keeps the tensor observation,
    exits and spawns. The three replay highway-env's reset and spawn draws in C++
    (:mod:`.native_draws`), bit for bit numpy's.

    Args:
        scenario: one of ``NATIVE_SCENARIOS``.
        params: its constants.
        device: must be the CPU.
        threads: threads over the worlds (default: ``torch.get_num_threads()`` at each
            step).

    Returns:
        The mode.

    Raises:
        ValueError: another scenario, a GPU, or a config the C++ step cannot hold
            (:func:`load_native`).
        NativeBuildError: no C++ compiler (:func:`torchrl_grpo.sim.native.load_library`).

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> mode = native_mode("highway-fast-v0", tensor_params("highway-fast-v0"),
        ...                    torch.device("cpu"))
        >>> callable(mode.observe)
        True
    """
    if scenario not in NATIVE_SCENARIOS:
        raise ValueError(
            f"the C++ step covers {NATIVE_SCENARIOS}, not {scenario!r} "
            "(its step stays the tensor one: TensorHighwayEnv.eager())"
        )
    if device.type != "cpu":
        raise ValueError(f"the C++ step runs on the CPU, not on {device}")
    load_native(scenario, params)  # a missing compiler or a config it cannot hold: here
    if scenario in ROUTED_NATIVE_SCENARIOS:
        eager = eager_mode(tensor_model(scenario), params, device)
        if scenario == "intersection-v0":
            frames = functools.partial(native_frames, threads=threads)
            draws = IntersectionDraws(native_spawn_draws, native_ego_draws)
            return eager._replace(
                name="native",
                step=functools.partial(eager.step, frames=frames, draws=draws),
                fresh=functools.partial(eager.fresh, frames=frames, draws=draws),
            )
        step = functools.partial(routed_step, params=params, threads=threads)
        # The reset draws replayed in C++ too, bit for bit.
        replay = native_merge_draws if scenario == "merge-v0" else native_roundabout_draws
        fresh = functools.partial(eager.fresh, replay=replay)
        return eager._replace(name="native", step=step, fresh=fresh)
    return StepMode(
        "native",
        functools.partial(native_step, params=params, threads=threads),
        functools.partial(native_observe, params=params, threads=threads),
        functools.partial(native_fresh, params=params),
    )


def load_native(scenario: str, params=None) -> None:
    """Build (or load) the C++ step of ``scenario``, and check that it can hold ``params``.

    Args:
        scenario: one of ``NATIVE_SCENARIOS``.
        params: its constants (:func:`~torchrl_grpo.envs.tensor_params`); ``None``: only
            build.

    Raises:
        NativeBuildError: no C++ compiler, or it failed.
        ValueError: ``params`` hold a config the C++ step cannot, such as more than 16
            target speeds.

    Example:
        >>> from torchrl_grpo.envs import tensor_params
        >>> load_native("roundabout-v0", tensor_params("roundabout-v0"))
    """
    routed = scenario in ROUTED_NATIVE_SCENARIOS
    (load_routed_library if routed else load_library)()
    if routed:
        load_draws_library()
    if params is not None:
        (routed_road if routed else native_params)(params)
        if scenario == "intersection-v0":
            rules_of(params)
