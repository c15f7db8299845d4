"""The CartPole codec, reseeding states, and a user's own highway-env vehicle class."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from env_helpers import (
    assert_bitwise_equal,
    assert_same_run,
    bit_differences,
    careful_actions,
    faithful_copy,
    random_actions,
    restore,
    run,
    runs_differ,
)
from highway_env.vehicle.behavior import IDMVehicle
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_grpo.envs import (
    CartPoleStateCodec,
    Field,
    HighwayEnv,
    SnapshotEnv,
    SnapshotError,
    StateCapacityError,
    StateCodec,
    StateCorruptedError,
    StateMismatchError,
    UnknownFieldError,
    register_vehicle_class,
)
from torchrl_grpo.envs.core.gym_state import encode_rng, seeded_rng_words
from torchrl_grpo.envs.highway import schema


# ---------------------------------------------------------------- CartPole
def cartpole(seed=0):
    return SnapshotEnv("CartPole-v1", seed=seed)


def test_cartpole_specs_and_codec():
    env = cartpole()
    assert isinstance(env.codec, CartPoleStateCodec)
    check_env_specs(env)
    state = env.get_state()
    assert all(isinstance(v, torch.Tensor) for v in state.values(True, True))
    assert env.state_spec["state"].is_in(state)


def test_cartpole_restore_replays_past_termination():
    """60 random steps: CartPole terminates early and keeps stepping (steps_beyond_terminated)."""
    env = cartpole()
    env.reset()
    actions = random_actions(env, 65, seed=2)
    run(env, actions[:5])
    snapshot = env.get_state()
    ref, ref_final = run(env, actions[5:])
    assert any(bool(o["terminated"]) for o in ref), "the run should reach termination"
    assert bit_differences(snapshot, ref_final)
    for target, what in ((env, "same env"), (cartpole(seed=9), "fresh env")):
        restore(target, snapshot)
        assert_bitwise_equal(target.get_state(), snapshot, f"{what}: right after restore")
        got, final = run(target, actions[5:])
        assert_same_run(ref, got, what)
        assert_bitwise_equal(final, ref_final, f"{what}: final state")


def test_cartpole_rng_and_time_limit_are_part_of_the_state():
    env = cartpole()
    env.reset()
    snapshot = env.get_state()
    next_episode = env.reset()
    other = cartpole(seed=5)
    own = other.reset()
    restore(other, snapshot)
    assert_bitwise_equal(other.reset(), next_episode, "fresh episode after restore")
    assert bit_differences(own, next_episode)

    # TimeLimit(500): a state whose counter says 499 truncates at the next step.
    nearly = faithful_copy(snapshot)
    nearly["sim", "wrappers", "elapsed_steps"].fill_(499)
    restore(other, nearly)
    assert other.step(TensorDict(action=torch.tensor(0)))["next", "truncated"].item()
    restore(other, snapshot)
    assert not other.step(TensorDict(action=torch.tensor(0)))["next", "truncated"].item()


@pytest.mark.parametrize("bad", ["nan-physics", "truncated", "wrong-dtype", "highway-state"])
def test_cartpole_bad_states_leave_it_untouched(bad):
    env, twin = cartpole(), cartpole()
    actions = random_actions(env, 8, seed=4)
    run(env, actions[:3])
    run(twin, actions[:3])
    state = env.get_state()
    broken = faithful_copy(state)
    if bad == "nan-physics":
        broken["sim", "physics"][2] = torch.tensor(float("nan"), dtype=torch.float64).view(
            torch.int64
        )
        error, match = StateCorruptedError, "non-finite"
    elif bad == "truncated":
        del broken["sim", "steps_beyond_terminated"]
        error, match = StateCorruptedError, "steps_beyond_terminated"
    elif bad == "wrong-dtype":
        broken["sim", "physics"] = broken["sim", "physics"].float()
        error, match = StateCorruptedError, "physics.*dtype"
    else:
        broken = HighwayEnv("merge-v0", seed=0).get_state()
        error, match = SnapshotError, "."
    with pytest.raises(error, match=match):
        restore(env, broken)
    assert_bitwise_equal(env.get_state(), state, "after the error")
    out, final = run(env, actions[3:])
    ref, ref_final = run(twin, actions[3:])
    assert_same_run(ref, out, "after the error")
    assert_bitwise_equal(final, ref_final, "final state")


# ---------------------------------------------------------------- reseeding
def test_reseeded_intersection_state_replays_its_own_traffic():
    """intersection-v0 spawns vehicles from its generator at every step."""
    env = HighwayEnv("intersection-v0", seed=1)
    actions = careful_actions(env, 12)
    run(env, actions[:2])
    state = env.get_state()
    original = faithful_copy(state)
    a, again, other = (env.reseed_state(state, s) for s in (11, 11, 12))
    assert not bit_differences(state, original), "reseeding modified its input"
    assert bit_differences(state, a) == [("sim", "env", "rng")]
    assert_bitwise_equal(a, again, "two reseeds with one seed")

    def replay(start):
        restore(env, start)
        return run(env, actions[2:])

    ref, ref_final = replay(state)
    got, final = replay(a)
    got_again, final_again = replay(again)
    _, other_final = replay(other)
    assert_same_run(got, got_again, "same seed")
    assert_bitwise_equal(final, final_again, "same seed: final state")
    # Other spawns: the vehicles differ (the ego's own outputs may well not).
    assert ("sim", "entities", "f64") in bit_differences(final, ref_final)
    assert ("sim", "entities", "f64") in bit_differences(final, other_final)
    # The original still replays as it did.
    assert_same_run(ref, replay(original)[0], "original after reseeding")


def test_reseeded_generator_is_the_seed_stream():
    env = cartpole()
    state = env.get_state()
    new = env.reseed_state(state, 7)
    assert torch.equal(new["sim", "rng"], seeded_rng_words(7))
    words = np.zeros(10, dtype=np.int64)
    encode_rng(np.random.default_rng(7), words)
    assert words.tolist() == new["sim", "rng"].tolist()
    # CartPole draws its next episode from the generator: the episode of reset(seed=7).
    restore(env, new)
    fresh = cartpole()
    fresh.set_seed(7)
    assert_bitwise_equal(env.reset().exclude("state"), fresh.reset().exclude("state"), "episode")


def test_reseed_state_batches_and_errors():
    env = cartpole()
    state = env.get_state()
    both = env.reseed_state(torch.stack([state, state]), [1, 2])
    assert_bitwise_equal(both[1], env.reseed_state(state, 2), "row 1")
    with pytest.raises(ValueError, match="as many seeds"):
        env.reseed_state(torch.stack([state, state]), [1])
    with pytest.raises(ValueError, match="non-negative"):
        env.reseed_state(state, -1)
    with pytest.raises(StateCorruptedError, match="truncated"):
        env.reseed_state(state.exclude("sim"), 1)
    merge = HighwayEnv("merge-v0", seed=0)
    with pytest.raises(StateMismatchError):
        HighwayEnv("intersection-v0", seed=0).reseed_state(merge.get_state(), 1)


class _NoReseedCodec(CartPoleStateCodec):
    reseed = StateCodec.reseed


def test_codecs_without_reseed_say_so():
    env = SnapshotEnv("CartPole-v1", codec=_NoReseedCodec(), seed=0)
    with pytest.raises(NotImplementedError, match="_NoReseedCodec"):
        env.reseed_state(env.get_state(), 1)


# ---------------------------------------------------------------- a user's vehicle class
class PatientIDM(IDMVehicle):
    """An IDM driver whose patience runs out every few frames: then it wants 1 m/s more."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.patience = 2.0

    def act(self, action=None):
        self.patience -= 1.0
        if self.patience <= 0:
            self.target_speed += 1.0
            self.patience = 2.0 + float(self.lane_index[2])
        super().act(action)


PATIENT_CONFIG = {"other_vehicles_type": f"{PatientIDM.__module__}.{PatientIDM.__qualname__}"}


@pytest.fixture
def isolated_registry(monkeypatch):
    """Registrations made by a test are undone afterwards (other envs keep their layout)."""
    monkeypatch.setattr(schema, "FIELDS", dict(schema.FIELDS))
    monkeypatch.setattr(schema, "VEHICLE_CLASSES", list(schema.VEHICLE_CLASSES))


def _patient_env(seed):
    env = HighwayEnv("highway-fast-v0", config=PATIENT_CONFIG, seed=seed)
    others = env.gym_env.unwrapped.road.vehicles[1:]
    assert others and all(type(v) is PatientIDM for v in others)
    return env


def _patience(env):
    return [v.patience for v in env.gym_env.unwrapped.road.vehicles[1:]]


def test_registered_vehicle_class_with_an_extra_field(isolated_registry):
    register_vehicle_class(PatientIDM, {"patience": Field("float")})
    env = _patient_env(seed=0)
    env.reset()
    actions = random_actions(env, 28, seed=6)
    run(env, actions[:3])
    snapshot, patience = env.get_state(), _patience(env)
    ref, ref_final = run(env, actions[3:])

    fresh = _patient_env(seed=8)
    restore(fresh, snapshot)
    assert _patience(fresh) == patience
    assert all(type(v) is PatientIDM for v in fresh.gym_env.unwrapped.road.vehicles[1:])
    got, final = run(fresh, actions[3:])
    assert_same_run(ref, got, "custom vehicles")
    assert_bitwise_equal(final, ref_final, "final state with custom vehicles")

    # The field decides the future, so a codec that dropped it would be caught above.
    restore(fresh, snapshot)
    for vehicle in fresh.gym_env.unwrapped.road.vehicles[1:]:
        vehicle.patience += 5.0
    impatient, _ = run(fresh, actions[3:])
    assert runs_differ(ref, impatient)


def test_unregistered_vehicle_class_fails_loudly_when_the_env_is_built(isolated_registry):
    with pytest.raises(UnknownFieldError, match="PatientIDM is not registered"):
        _patient_env(seed=0)


def test_registered_class_without_its_field_names_the_field_when_the_env_is_built(
    isolated_registry,
):
    # Issue #20: caught at the first snapshot before, after the env was built and used
    register_vehicle_class(PatientIDM)
    with pytest.raises(UnknownFieldError, match=r"PatientIDM\.patience is not a field"):
        _patient_env(seed=0)


def test_a_road_larger_than_the_padding_still_names_the_field_when_the_env_is_built(
    isolated_registry,
):
    # The road cannot be packed (that stays a capacity error at the snapshot), but its
    # objects' classes and attribute names are checked at the build all the same.
    register_vehicle_class(PatientIDM)
    with pytest.raises(UnknownFieldError, match=r"PatientIDM\.patience is not a field"):
        HighwayEnv("highway-fast-v0", config=PATIENT_CONFIG, seed=0, max_vehicles=2)
    schema.VEHICLE_CLASSES.remove(PatientIDM)
    with pytest.raises(UnknownFieldError, match="PatientIDM is not registered"):
        HighwayEnv("highway-fast-v0", config=PATIENT_CONFIG, seed=0, max_vehicles=2)
    # a known road too large for its padding builds, and fails at the snapshot as before
    env = HighwayEnv("highway-fast-v0", seed=0, max_vehicles=2)
    with pytest.raises(StateCapacityError, match="pads to 2"):
        env.get_state()


def test_an_attribute_added_after_the_build_is_caught_at_the_snapshot(isolated_registry):
    env = HighwayEnv("highway-fast-v0", seed=0)
    env.gym_env.unwrapped.road.vehicles[1].patience = 1.0
    with pytest.raises(UnknownFieldError, match=r"IDMVehicle\.patience is not a field"):
        env.get_state()


def test_registering_a_known_field_with_another_kind_is_refused(isolated_registry):
    with pytest.raises(ValueError, match="timer"):
        register_vehicle_class(PatientIDM, {"timer": Field("int")})
    assert PatientIDM not in schema.VEHICLE_CLASSES
