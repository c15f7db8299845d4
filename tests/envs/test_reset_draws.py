"""The reset draws replayed from highway-env's generator words, against numpy's own calls.

The C++ replays (sim/draws_native.cpp: merge-v0's and roundabout-v0's resets,
intersection-v0's spawns and ego) against the numpy replays, and those against
highway-env's own calls (roundabout-v0's destination drawn as ``integers`` where
highway-env calls ``choice``): each bit for bit, draws and generator words after them.
"""

from __future__ import annotations

import importlib.machinery

import numpy as np
import pytest
import torch

from torchrl_grpo.envs import StateCorruptedError, TensorHighwayEnv
from torchrl_grpo.envs.core.gym_state import encode_rng, restore_rng, seeded_rng_words
from torchrl_grpo.envs.highway.intersection_bridge import (
    HOST_DRAWS,
    IntersectionDraws,
    ego_draws,
    intersection_fresh,
    spawn_draws,
)
from torchrl_grpo.envs.highway.merge_bridge import merge_draws
from torchrl_grpo.envs.highway.native_draws import (
    native_ego_draws,
    native_merge_draws,
    native_roundabout_draws,
    native_spawn_draws,
)
from torchrl_grpo.envs.highway.roundabout_bridge import roundabout_draws
from torchrl_grpo.envs.highway.tensor_params import tensor_params
from torchrl_grpo.sim import draws_native
from torchrl_grpo.sim.intersection_reset import empty_intersection
from torchrl_grpo.sim.native_build import NativeBuildError


def generator_words(count: int) -> torch.Tensor:
    """Seeded generators, every third one a 32-bit draw further on (``has_uint32`` = 1)."""
    words = torch.stack([seeded_rng_words(s) for s in range(count)]).numpy().copy()
    generator = np.random.default_rng()
    for row in range(0, count, 3):
        restore_rng(generator, words[row])
        generator.integers(2)
        encode_rng(generator, words[row])
    return torch.from_numpy(words)


def test_the_draws_and_the_words_after_are_numpys():
    words = generator_words(600)
    assert (words[:, 8] == 1).any() and (words[:, 8] == 0).any()
    rows = torch.rand(600, generator=torch.Generator().manual_seed(0)) < 0.7
    draws, after = native_merge_draws(words, rows)
    expected_draws, expected_after = merge_draws(words, rows)
    assert torch.equal(draws, expected_draws) and torch.equal(after, expected_after)
    assert torch.equal(after[~rows], words[~rows]) and not torch.equal(after[rows], words[rows])
    # By hand, highway-env's seed 0: lane 1, -2.30 m, -0.92 m/s for the first car.
    first, _ = native_merge_draws(seeded_rng_words(0).unsqueeze(0), torch.tensor([True]))
    assert first[0, :3].tolist() == [1.0, -2.302132862361297, -0.9180529521276106]


def test_corrupted_words_are_refused_by_row_as_numpys_replay_refuses_them():
    words = generator_words(4)
    words[2, 4] += 1  # an even increment: no state numpy makes
    rows = torch.tensor([True, False, True, True])
    with pytest.raises(StateCorruptedError, match="highway.rng of row 2: the PCG64 increment"):
        native_merge_draws(words, rows)
    with pytest.raises(StateCorruptedError, match="highway.rng of row 2: the PCG64 increment"):
        merge_draws(words, rows)
    native_merge_draws(words, torch.tensor([True, True, False, True]))  # row 2 not reset
    with pytest.raises(ValueError, match=r"\[B, 10\] with \[B\] rows, got \(4, 9\)"):
        native_merge_draws(words[:, :9], rows)


def _rows(count: int, seed: int) -> torch.Tensor:
    return torch.rand(count, generator=torch.Generator().manual_seed(seed)) < 0.7


def test_the_cpp_roundabout_draws_are_numpys():
    params = tensor_params("roundabout-v0")
    words, rows = generator_words(600), _rows(600, 1)
    native = native_roundabout_draws(words, rows, params)
    assert all(map(torch.equal, native, roundabout_draws(words, rows, params)))
    assert torch.equal(native[1][~rows], words[~rows])


@pytest.mark.parametrize("probability", [0.0, 0.6, 1.0])
@pytest.mark.parametrize("go_straight", [False, True])
def test_the_cpp_spawn_draws_are_numpys(probability, go_straight):
    # A spawn's choice(4, 2, replace=False) is numpy's Floyd sample and shuffle, its
    # normals numpy's ziggurat: the numpy replay calls Generator.choice and normal.
    params = tensor_params("intersection-v0")
    words, rows = generator_words(600), _rows(600, 2)
    native = native_spawn_draws(words, rows, params, probability, go_straight)
    host = spawn_draws(words, rows, params, probability, go_straight)
    assert all(map(torch.equal, native, host))
    spawned = rows & (native[0][:, 0] <= probability)
    assert int(spawned.sum()) == pytest.approx(420 * probability, abs=60)
    assert torch.equal(native[1][~rows], words[~rows]) and torch.equal(
        native[2][~rows], words[~rows]
    )
    assert torch.equal(native[1][~spawned], native[2][~spawned])  # no car: nothing more drawn
    assert not (native[1] == native[2]).all(-1)[spawned].any()  # a kept car: its exponent
    if spawned.any():
        corner, goal = native[0][spawned, 1], native[0][spawned, 2]
        assert (corner != goal).all()
        assert ((goal - corner) % 4 == 2).all() == go_straight


@pytest.mark.parametrize("destination", ["o1", None])  # the config's, a random one
def test_the_cpp_ego_draws_are_numpys(destination):
    params = tensor_params("intersection-v0", {"destination": destination})
    words, rows = generator_words(300), _rows(300, 3)
    native = native_ego_draws(words, rows, params)
    assert all(map(torch.equal, native, ego_draws(words, rows, params)))
    assert len(set(native[0][rows].tolist())) == (1 if destination else 3)


def test_the_cpp_draws_refuse_corrupted_words_naming_the_row():
    params = tensor_params("intersection-v0")
    words = generator_words(4)
    words[1, 8] = 2  # has_uint32 neither 0 nor 1
    with pytest.raises(StateCorruptedError, match="highway.rng of row 1"):
        native_spawn_draws(words, torch.ones(4, dtype=torch.bool), params, 0.6)
    with pytest.raises(StateCorruptedError, match="highway.rng of row 1"):
        native_ego_draws(words, torch.ones(4, dtype=torch.bool), params)
    unread = torch.tensor([True, False, True, True])
    assert torch.equal(native_spawn_draws(words, unread, params, 0.6)[1][1], words[1])


def test_a_numpy_without_its_c_random_library_is_named(tmp_path, monkeypatch):
    # The C++ draws link numpy's libnpyrandom; a numpy that lacks it gets a build error
    # that names the missing file (env.backend=auto then steps with tensors).
    (tmp_path / "numpy").mkdir()
    (tmp_path / "numpy" / "__init__.py").write_text("")
    spec = importlib.machinery.ModuleSpec("numpy", None, origin=str(tmp_path / "numpy/__init__.py"))
    monkeypatch.setattr(draws_native.importlib.util, "find_spec", lambda name: spec)
    with pytest.raises(NativeBuildError, match=r"libnpyrandom\.a.*not found"):
        draws_native.numpy_random_library()


def test_an_intersection_reset_names_a_bad_rows_place_in_the_batch():
    # Only the rows that reset are built: the error still names the row of the batch.
    params = tensor_params("intersection-v0")
    words = generator_words(4)
    words[2, 4] += 1  # an even increment
    world = empty_intersection(4, params)
    rows = torch.tensor([False, False, True, False])
    for draws in (HOST_DRAWS, IntersectionDraws(native_spawn_draws, native_ego_draws)):
        with pytest.raises(StateCorruptedError, match="highway.rng of row 2: the PCG64"):
            intersection_fresh(world, rows, words, None, params, draws=draws)
    fresh, after, _ = intersection_fresh(world, ~rows, words, None, params)  # row 2 not read
    assert torch.equal(after[2], words[2]) and not fresh.vehicles.present[2].any()


@pytest.mark.parametrize(
    "scenario, actions", [("merge-v0", 5), ("roundabout-v0", 5), ("intersection-v0", 3)]
)
def test_the_cpp_step_draws_as_the_tensor_step_does(scenario, actions):
    # Resets (and intersection-v0's spawns, every step) leave the same generator words.
    # intersection-v0's C++ frames round a sine as libm does: observations agree to 1e-9.
    native = TensorHighwayEnv(scenario, num_envs=32, seed=5, native=True, dtype=torch.float64)
    tensor = TensorHighwayEnv(scenario, num_envs=32, seed=5, dtype=torch.float64)
    torch.testing.assert_close(
        native.reset()["observation"], tensor.reset()["observation"], rtol=0, atol=1e-9
    )
    steps = torch.randint(0, actions, (12, 32), generator=torch.Generator().manual_seed(1))
    a, b, ended = native.reset(), tensor.reset(), 0
    for action in steps:  # random actions crash and end episodes: many resets
        out, a = native.step_and_maybe_reset(a.set("action", action))
        ended += int(out["next", "done"].sum())
        b = tensor.step_and_maybe_reset(b.set("action", action))[1]
    assert ended >= 5
    assert torch.equal(native.get_state()["highway", "rng"], tensor.get_state()["highway", "rng"])


def test_the_roundabouts_draws_are_those_of_highway_envs_choice():
    params = tensor_params("roundabout-v0")
    names = [params.road.destinations[d] for d in params.traffic.destinations]
    low, high = params.idm.delta_range
    words = generator_words(300)
    draws, after = roundabout_draws(words, torch.ones(300, dtype=torch.bool), params)
    generator = np.random.default_rng()
    for row in range(300):
        restore_rng(generator, words[row].numpy())
        expected = []
        for _ in range(4):  # RoundaboutEnv._make_vehicles' calls, choice as it makes it
            expected += [generator.normal(), generator.normal()]
            expected += [float(names.index(str(generator.choice(names))))]
            expected += [generator.uniform(low=low, high=high)]
        assert draws[row].tolist() == expected
        state = np.zeros(10, dtype=np.int64)
        encode_rng(generator, state)
        assert after[row].tolist() == state.tolist()
