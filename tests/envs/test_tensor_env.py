"""TensorHighwayEnv: HighwayEnv's interface over B batched worlds, exact restores, clear errors."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import (
    HighwayEnv,
    StateCorruptedError,
    StateMismatchError,
    TensorHighwayEnv,
)
from torchrl_grpo.envs.highway.tensor_params import TENSOR_SCENARIOS

SMALL = {"vehicles_count": 8}


def actions(batch: int, steps: int, seed: int = 0) -> list[TensorDict]:
    g = torch.Generator().manual_seed(seed)
    return [
        TensorDict(action=torch.randint(0, 5, (batch,), generator=g), batch_size=[batch])
        for _ in range(steps)
    ]


def play(env: TensorHighwayEnv, script: list[TensorDict]) -> list[TensorDict]:
    return [env.step(a.clone())["next"] for a in script]


@pytest.mark.parametrize(
    ("scenario", "kwargs"),
    [
        ("highway-fast-v0", {}),
        ("highway-fast-v0", {"dtype": torch.float64, "return_state": True}),
        ("highway-fast-v0", {"categorical_action_encoding": False}),
        ("highway-v0", {"config": SMALL}),
    ],
)
def test_check_env_specs(scenario, kwargs):
    check_env_specs(TensorHighwayEnv(scenario, num_envs=4, seed=0, **kwargs))


@pytest.mark.parametrize("scenario", TENSOR_SCENARIOS)
def test_same_keys_and_specs_as_highway_env(scenario):
    tensor = TensorHighwayEnv(scenario, num_envs=3, seed=0)
    highway = HighwayEnv(scenario, seed=0)
    for name in ("observation_spec", "reward_spec", "done_spec", "action_spec"):
        a, b = getattr(tensor, name), getattr(highway, name)
        assert a.shape[1:] == b.shape if hasattr(a, "shape") else True
        if hasattr(b, "keys"):
            assert set(a.keys(True, True)) == set(b.keys(True, True))
            for key in b.keys(True, True):
                assert a[key].shape[1:] == b[key].shape, key
                assert a[key].dtype == b[key].dtype, key
        else:
            assert (a.dtype, type(a)) == (b.dtype, type(b))


def test_float64_makes_every_float_spec_float64():
    env = TensorHighwayEnv(num_envs=2, dtype=torch.float64)
    specs = [env.full_observation_spec, env.full_reward_spec, env.full_state_spec]
    floats = [
        s.dtype for spec in specs for _, s in spec.items(True, True) if s.dtype.is_floating_point
    ]
    assert floats and set(floats) == {torch.float64}


def test_restore_and_replay_is_bitwise():
    env = TensorHighwayEnv(num_envs=6, seed=1)
    env.reset()
    play(env, actions(6, 3, seed=5))
    state = env.get_state()
    script = actions(6, 12, seed=7)
    first = play(env, script)
    after = env.get_state()
    env.reset(TensorDict(state=state, batch_size=[6]), set_state=True)
    second = play(env, script)
    for a, b in zip(first, second, strict=True):
        assert (a == b).all()
    assert (env.get_state() == after).all()


def test_branches_are_copies_along_the_batch():
    env = TensorHighwayEnv(num_envs=8, seed=2)
    env.reset()
    roots = env.get_state()[:2].repeat_interleave(4, 0)  # 2 roots x 4 branches
    env.reset(TensorDict(state=roots, batch_size=[8]), set_state=True)
    same = TensorDict(action=torch.tensor([3, 3, 3, 3, 4, 4, 4, 4]), batch_size=[8])
    outs = [env.step(same.clone())["next", "observation"] for _ in range(5)]
    for obs in outs:
        assert torch.equal(obs[0], obs[3]) and torch.equal(obs[4], obs[7])


def test_partial_reset_touches_only_masked_rows():
    env = TensorHighwayEnv(num_envs=4, seed=3)
    env.reset()
    play(env, actions(4, 2))
    before = env.get_state()
    mask = torch.tensor([True, False, True, False]).unsqueeze(-1)
    env.reset(TensorDict(_reset=mask, batch_size=[4]))
    after = env.get_state()
    assert (after[1] == before[1]).all() and (after[3] == before[3]).all()
    assert after["steps"].tolist() == [0, before["steps"][1].item(), 0, before["steps"][3].item()]
    assert not torch.equal(after["vehicles", "x"][0], before["vehicles", "x"][0])


def test_rollout_resets_finished_rows_into_new_episodes():
    env = TensorHighwayEnv(num_envs=16, seed=4)
    slower = lambda td: td.set("action", torch.full((16,), 4))  # noqa: E731 - rarely crashes
    td = env.rollout(35, slower, break_when_any_done=False)  # past the 30 s duration
    assert td.batch_size == torch.Size([16, 35])
    assert bool(td["next", "truncated"].any())
    assert bool((td["next", "done"].sum(1) >= 1).all())
    assert bool((env.get_state()["rng", "counter"] >= 2).all())  # first episode + a new one


def test_seeds_reproduce_and_differ():
    def first_positions(seed):
        env = TensorHighwayEnv(num_envs=3, seed=seed)
        env.reset()
        return env.get_state()["vehicles", "x"]

    assert torch.equal(first_positions(0), first_positions(0))
    assert not torch.equal(first_positions(0), first_positions(1))
    env = TensorHighwayEnv(num_envs=3, seed=0)
    env.set_seed(0)
    env.reset()
    assert torch.equal(env.get_state()["vehicles", "x"], first_positions(0))


@pytest.mark.parametrize(
    ("scenario", "config", "match"),
    [
        ("racetrack-v0", None, "covers"),
        ("highway-fast-v0", {"lanes_cout": 3}, "did you mean 'lanes_count'"),
        ("highway-fast-v0", {"manual_control": True}, "manual_control"),
        ("highway-fast-v0", {"controlled_vehicles": 2}, "controlled_vehicles"),
        (
            "highway-fast-v0",
            {"observation": {"type": "Kinematics", "order": "shuffled"}},
            "shuffled",
        ),
        (
            "highway-fast-v0",
            {"observation": {"type": "Kinematics", "features": ["lat_off"]}},
            "features",
        ),
        ("highway-fast-v0", {"observation": {"type": "OccupancyGrid"}}, "Kinematics"),
        ("highway-fast-v0", {"action": {"type": "ContinuousAction"}}, "DiscreteMetaAction"),
        ("highway-fast-v0", {"lanes_count": 0}, "lanes_count"),
        ("highway-fast-v0", {"initial_lane_id": 5}, "initial_lane_id"),
        ("highway-fast-v0", {"show_trajectories": True}, "show_trajectories"),
    ],
)
def test_uncovered_configs_are_value_errors_naming_the_key(scenario, config, match):
    with pytest.raises(ValueError, match=match):
        TensorHighwayEnv(scenario, config, num_envs=2)


def _corrupt(state, key, value):
    bad = state.clone()
    bad.get(key)[1].fill_(value) if bad.get(key).ndim > 1 else bad.get(key).__setitem__(1, value)
    return bad


@pytest.mark.parametrize(
    ("edit", "error", "match"),
    [
        (lambda s: s[:2], RuntimeError, "env.batch_size"),  # TorchRL's own check
        (lambda s: s.exclude(("vehicles", "timer")), StateCorruptedError, "vehicles.timer"),
        (
            lambda s: s.apply(lambda t: t.double() if t.dtype == torch.float32 else t),
            StateCorruptedError,
            "float64",
        ),
        (
            lambda s: _corrupt(s, ("vehicles", "speed"), float("nan")),
            StateCorruptedError,
            "vehicles.speed",
        ),
        (lambda s: _corrupt(s, ("vehicles", "x"), float("inf")), StateCorruptedError, "vehicles.x"),
        (lambda s: _corrupt(s, ("vehicles", "lane"), 7), StateCorruptedError, "vehicles.lane"),
        (lambda s: _corrupt(s, ("highway", "rng"), 0), StateCorruptedError, "highway.rng"),
        (lambda s: _corrupt(s, "fingerprint", 1), StateMismatchError, "another scenario"),
    ],
)
def test_bad_states_are_refused_and_the_env_stays_usable(edit, error, match):
    env = TensorHighwayEnv(num_envs=3, seed=0)
    env.reset()
    good = env.get_state()
    bad = edit(good)
    with pytest.raises(error, match=match):
        env.reset(TensorDict(state=bad, batch_size=bad.batch_size), set_state=True)
    assert (env.get_state() == good).all()  # nothing was restored
    env.step(TensorDict(action=torch.ones(3, dtype=torch.int64), batch_size=[3]))
    env.reset(TensorDict(state=good, batch_size=[3]), set_state=True)
    assert (env.get_state() == good).all()


def test_a_state_of_another_config_is_a_mismatch():
    other = TensorHighwayEnv(config={"lanes_count": 4}, num_envs=2)
    other.reset()
    env = TensorHighwayEnv(num_envs=2)
    with pytest.raises(StateMismatchError):
        env.validate_state(other.get_state())


def test_value_checks_can_be_turned_off_but_not_structure_checks():
    env = TensorHighwayEnv(num_envs=2, check_states=False)
    env.reset()
    state = env.get_state()
    state["vehicles", "speed"][0, 3] = float("nan")
    env.reset(TensorDict(state=state, batch_size=[2]), set_state=True)  # accepted
    with pytest.raises(StateCorruptedError, match="truncated"):
        env.validate_state(state.exclude("time"))


def test_reseeded_states_draw_new_episodes_but_keep_the_world():
    env = TensorHighwayEnv(num_envs=2, seed=0)
    env.reset()
    state = env.get_state()
    a, b = env.reseed_state(state, [5, 6]), env.reseed_state(state, [5, 6])
    assert (a == b).all()
    assert torch.equal(a["vehicles", "x"], state["vehicles", "x"])
    assert not torch.equal(a["rng", "key"], state["rng", "key"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_rollout_matches_cpu():
    cpu = TensorHighwayEnv(num_envs=8, seed=0, dtype=torch.float64)
    gpu = TensorHighwayEnv(num_envs=8, seed=0, dtype=torch.float64, device="cuda")
    a = cpu.rollout(
        10,
        break_when_any_done=False,
        policy=lambda td: td.set("action", torch.ones(8, dtype=torch.int64)),
    )
    b = gpu.rollout(
        10,
        break_when_any_done=False,
        policy=lambda td: td.set("action", torch.ones(8, dtype=torch.int64, device="cuda")),
    )
    assert torch.allclose(a["next", "observation"], b["next", "observation"].cpu(), atol=1e-9)


def test_asking_for_cuda_without_a_gpu_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="cuda"):
        TensorHighwayEnv(num_envs=2, device="cuda")


@pytest.mark.parametrize("dense", [False, True])
def test_compile_traces_the_step_once_and_keeps_the_bits(dense):
    # compile= in the constructor is TorchRL's keyword: it must reach this env's compile
    # (pure step functions, static shapes: the dense stages between the compacted ones,
    # or the whole dense step), not TorchRL's whole step_and_maybe_reset, which
    # recompiled at every step here. The eager backend traces without code generation.
    from torch._dynamo.utils import counters

    torch._dynamo.reset()
    compiled = TensorHighwayEnv(num_envs=4, seed=3, compile={"backend": "eager", "dense": dense})
    eager = TensorHighwayEnv(num_envs=4, seed=3)
    assert "_compiled_step_and_maybe_reset" not in vars(compiled)
    script = actions(4, 5, seed=1)
    graphs = []
    for a in script:
        torch.testing.assert_close(compiled.step(a.clone()), eager.step(a.clone()), rtol=0, atol=0)
        graphs.append(counters["stats"]["unique_graphs"])
    assert graphs[0] >= 1 and graphs[-1] == graphs[0]  # traced at the first step only
    for key, value in eager.get_state().items(True, True):
        assert torch.equal(compiled.get_state()[key], value), key
    assert compiled.eager() is compiled
    torch.testing.assert_close(compiled.step(script[0].clone()), eager.step(script[0].clone()))
