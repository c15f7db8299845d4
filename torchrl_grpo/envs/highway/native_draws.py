"""The reset and spawn draws of merge-v0, roundabout-v0 and intersection-v0, in C++.

Each function returns what its numpy replay on the host returns, bit for bit: the draws,
and the generator words after them (:func:`.merge_bridge.merge_draws`,
:func:`.roundabout_bridge.roundabout_draws`, :func:`.intersection_bridge.spawn_draws`,
:func:`.intersection_bridge.ego_draws`), with one call for all the worlds instead of a
generator per world (:mod:`torchrl_grpo.sim.draws_native`). The C++ steps
(``TensorHighwayEnv(..., native=True)``) use them; the numpy replays stay the tensor
path's, which needs no compiler.

Example:
    >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
    >>> from torchrl_grpo.envs.highway.merge_bridge import merge_draws
    >>> words, rows = seeded_rng_words(0).unsqueeze(0), torch.tensor([True])
    >>> all(torch.equal(a, b) for a, b in zip(native_merge_draws(words, rows),
    ...                                        merge_draws(words, rows)))
    True
"""

from __future__ import annotations

import torch

from torchrl_grpo.envs.core.gym_state import RNG_WORDS, check_rng_rows
from torchrl_grpo.envs.highway.tensor_params import tensor_params
from torchrl_grpo.sim.draws_native import load_draws_library
from torchrl_grpo.sim.intersection_params import IntersectionParams
from torchrl_grpo.sim.intersection_reset import SPAWN_DRAWS
from torchrl_grpo.sim.merge_reset import DRAWS as MERGE_DRAWS
from torchrl_grpo.sim.roundabout_params import RoundaboutParams
from torchrl_grpo.sim.roundabout_reset import DRAWS as ROUNDABOUT_DRAWS

__all__ = [
    "native_ego_draws",
    "native_merge_draws",
    "native_roundabout_draws",
    "native_spawn_draws",
]


def _host(words: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(words, rows)`` contiguous on the host, checked as the numpy replays check them.

    Raises:
        ValueError: words not ``[B, RNG_WORDS]`` with ``[B]`` rows.
        StateCorruptedError: a drawing row's words are no PCG64 state numpy makes
            (:func:`~torchrl_grpo.envs.core.gym_state.decode_rng`'s message, naming it).
    """
    host = words.detach().to("cpu", torch.int64).contiguous()
    drawing = rows.detach().to("cpu", torch.bool).contiguous()
    if host.dim() != 2 or host.shape[-1] != RNG_WORDS or drawing.shape != host.shape[:1]:
        raise ValueError(
            f"generator words are [B, {RNG_WORDS}] with [B] rows, got {tuple(host.shape)} "
            f"and {tuple(drawing.shape)}"
        )
    check_rng_rows(host, drawing)
    return host, drawing


def native_merge_draws(
    words: torch.Tensor, rows: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`.merge_bridge.merge_draws` in C++: ``([B, 3 * cars] draws, words after)``.

    Raises:
        StateCorruptedError: a reset row's words are not a PCG64 state numpy makes.
        NativeBuildError: no C++ compiler.

    Example:
        >>> # see the module's example
    """
    host, drawing = _host(words, rows)
    draws = torch.zeros(host.shape[0], MERGE_DRAWS, dtype=torch.float64)
    after = torch.empty_like(host)
    load_draws_library().merge_draws(
        host.data_ptr(), drawing.data_ptr(), host.shape[0], MERGE_DRAWS // 3, draws.data_ptr(),
        after.data_ptr(),
    )  # fmt: skip
    return draws.to(words.device), after.to(words.device)


def native_roundabout_draws(
    words: torch.Tensor, rows: torch.Tensor, params: RoundaboutParams | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`.roundabout_bridge.roundabout_draws` in C++: ``([B, 16] draws, words after)``.

    Raises:
        StateCorruptedError: a reset row's words are not a PCG64 state numpy makes.
        NativeBuildError: no C++ compiler.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> draws, _ = native_roundabout_draws(seeded_rng_words(0).unsqueeze(0),
        ...                                    torch.tensor([True]))
        >>> [round(d, 4) for d in draws[0, :4].tolist()]  # seed 0: the incoming car's
        [0.1257, -0.1321, 0.0, 3.5165]
    """
    params = params or tensor_params("roundabout-v0")
    host, drawing = _host(words, rows)
    draws = torch.zeros(host.shape[0], ROUNDABOUT_DRAWS, dtype=torch.float64)
    after = torch.empty_like(host)
    low, high = params.idm.delta_range
    load_draws_library().roundabout_draws(
        host.data_ptr(), drawing.data_ptr(), host.shape[0], ROUNDABOUT_DRAWS // 4,
        len(params.traffic.destinations), low, high, draws.data_ptr(), after.data_ptr(),
    )  # fmt: skip
    return draws.to(words.device), after.to(words.device)


def native_spawn_draws(
    words: torch.Tensor,
    rows: torch.Tensor,
    params: IntersectionParams,
    probability: float,
    go_straight: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`.intersection_bridge.spawn_draws` in C++: ``(draws, words if dropped, if kept)``.

    Raises:
        StateCorruptedError: a spawning row's words are not a PCG64 state numpy makes.
        NativeBuildError: no C++ compiler.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> params = tensor_params("intersection-v0")
        >>> words = seeded_rng_words(0).unsqueeze(0)
        >>> draws, dropped, stays = native_spawn_draws(words, torch.tensor([True]), params, 1.0)
        >>> [round(d, 4) for d in draws[0, :3].tolist()]  # it spawns: a corner, a destination
        [0.637, 3.0, 1.0]
    """
    host, drawing = _host(words, rows)
    draws = torch.empty(host.shape[0], SPAWN_DRAWS, dtype=torch.float64)
    dropped, stays = torch.empty_like(host), torch.empty_like(host)
    low, high = params.idm.delta_range
    load_draws_library().spawn_draws(
        host.data_ptr(), drawing.data_ptr(), host.shape[0], probability, int(go_straight), low,
        high, draws.data_ptr(), dropped.data_ptr(), stays.data_ptr(),
    )  # fmt: skip
    device = words.device
    return draws.to(device), dropped.to(device), stays.to(device)


def native_ego_draws(
    words: torch.Tensor, rows: torch.Tensor, params: IntersectionParams
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`.intersection_bridge.ego_draws` in C++: ``(destination, normal(1.0), words after)``.

    Raises:
        StateCorruptedError: a reset row's words are not a PCG64 state numpy makes.
        NativeBuildError: no C++ compiler.

    Example:
        >>> from torchrl_grpo.envs.core.gym_state import seeded_rng_words
        >>> params = tensor_params("intersection-v0")
        >>> goal, offset, _ = native_ego_draws(seeded_rng_words(0).unsqueeze(0),
        ...                                    torch.tensor([True]), params)
        >>> goal.tolist(), round(offset.item(), 4)  # the config's destination, o1
        ([1], 1.1257)
    """
    host, drawing = _host(words, rows)
    goal = torch.empty(host.shape[0], dtype=torch.int64)
    offset = torch.empty(host.shape[0], dtype=torch.float64)
    after = torch.empty_like(host)
    load_draws_library().ego_draws(
        host.data_ptr(), drawing.data_ptr(), host.shape[0], params.traffic.ego_destination,
        goal.data_ptr(), offset.data_ptr(), after.data_ptr(),
    )  # fmt: skip
    device = words.device
    return goal.to(device), offset.to(device), after.to(device)
