"""Shared helpers for the env tests: action sequences, fixed-length runs, bitwise comparisons.

Every comparison here is bitwise and independent of the library's own
``states_equal`` (a second, reference implementation): two tensors are equal when
their dtype, shape and raw bytes are (so NaN == NaN, and -0.0 != 0.0).
"""

from __future__ import annotations

import warnings

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_grpo.envs import HIGHWAY_SCENARIOS, TensorHighwayEnv
from torchrl_grpo.envs.core.bits import FLOAT_BITS

# highway-env flags its older scenario versions as out of date on every gym.make.
warnings.filterwarnings("ignore", message=".*is out of date.*")

SLOW_SCENARIOS = ("highway-v0",)  # ~180 ms per step: short runs by default
FAST_SCENARIOS = tuple(s for s in HIGHWAY_SCENARIOS if s not in SLOW_SCENARIOS)

# Steps run after the snapshot in the determinism matrix. lane-keeping-v0 (0.7 ms a
# step) runs to its TimeLimit of 200 and past it.
RUN_STEPS = {s: 30 for s in HIGHWAY_SCENARIOS}
RUN_STEPS["lane-keeping-v0"] = 205
RUN_STEPS["parking-v0"] = 60


# ---------------------------------------------------------------------- actions
def careful_actions(env, n: int) -> list[torch.Tensor]:
    """A policy that keeps episodes long: IDLE for discrete meta-actions, zeros otherwise."""
    spec = env.action_spec
    if not spec.dtype.is_floating_point:
        assert spec.space.n >= 3, "IDLE is action 1 of DiscreteMetaAction"
        return [torch.tensor(1, dtype=spec.dtype) for _ in range(n)]
    return [torch.zeros(spec.shape, dtype=spec.dtype) for _ in range(n)]


def random_actions(env, n: int, seed: int) -> list[torch.Tensor]:
    """A fixed random action sequence (its own generator: global RNGs are not touched)."""
    spec = env.action_spec
    gen = torch.Generator().manual_seed(seed)
    if not spec.dtype.is_floating_point:
        return [torch.randint(spec.space.n, (), generator=gen).to(spec.dtype) for _ in range(n)]
    low, high = spec.space.low, spec.space.high
    return [
        (low + (high - low) * torch.rand(spec.shape, generator=gen, dtype=torch.float64)).to(
            spec.dtype
        )
        for _ in range(n)
    ]


def actions_for(env, policy: str, n: int, seed: int = 0) -> list[torch.Tensor]:
    if policy == "careful":
        return careful_actions(env, n)
    if policy == "random":
        actions = random_actions(env, n, seed)
        if getattr(env, "scenario", None) == "two-way-v0":
            # highway-env 1.12.1 itself raises ZeroDivisionError in two-way-v0's reward once
            # LANE_LEFT (0) takes the ego onto the one-lane oncoming road (raw gym, seed 1,
            # these actions: step 31); the random policy there changes lanes rightwards only.
            actions = [a if int(a) != 0 else torch.ones_like(a) * 2 for a in actions]
        return actions
    raise ValueError(policy)


# ---------------------------------------------------------------------- running
def faithful_copy(td: TensorDictBase) -> TensorDictBase:
    """A leaf-by-leaf ``Tensor.clone()``: keeps every bit.

    (``TensorDict.clone()`` of a td with a device copies through
    ``torch._foreach_add(x, 0)``, which turns -0.0 into +0.0; see test_specs.)
    """
    return td.apply(torch.clone)


def run(env, actions) -> tuple[list[TensorDict], TensorDict]:
    """Step ``env`` through ``actions`` (past ``done``: highway-env keeps simulating).

    Returns the per-step outputs (the ``"next"`` entries, without any ``"state"``)
    and the complete state after the last step.
    """
    outputs = []
    for action in actions:
        out = env.step(TensorDict(action=action.clone()))
        outputs.append(out["next"].exclude("state"))
    return outputs, env.get_state()


def restore(env, state: TensorDictBase) -> TensorDict:
    """Restore through the TorchRL idiom, as users do; checks the input is left intact."""
    given = faithful_copy(state)
    out = env.reset(TensorDict(state=given), set_state=True)
    assert not bit_differences(given, state), "restoring modified the state it was given"
    return out


# ---------------------------------------------------------------------- comparing
def leaf_bits(td: TensorDictBase) -> dict:
    """``{key: (dtype, shape, raw bytes)}`` for every tensor leaf."""
    out = {}
    for key, value in td.items(include_nested=True, leaves_only=True):
        assert isinstance(value, torch.Tensor), f"{key!r} is not a tensor: {type(value)}"
        value = value.detach().cpu()
        if value.dtype.is_floating_point:
            # States hold floats as integer bit patterns: compare outputs in that form too.
            value = value.view(FLOAT_BITS[value.dtype])
        out[key] = (value.dtype, tuple(value.shape), value.numpy().tobytes())
    return out


def bit_differences(a: TensorDictBase, b: TensorDictBase) -> list:
    """Keys whose dtype, shape or bytes differ, plus keys present in only one of them."""
    bits_a, bits_b = leaf_bits(a), leaf_bits(b)
    keys = set(bits_a) | set(bits_b)
    return sorted((k for k in keys if bits_a.get(k) != bits_b.get(k)), key=str)


def assert_bitwise_equal(a: TensorDictBase, b: TensorDictBase, what: str = "") -> None:
    diffs = bit_differences(a, b)
    assert not diffs, f"{what} differs bitwise at {diffs}"


def assert_same_run(ref: list[TensorDict], got: list[TensorDict], what: str = "") -> None:
    """Same number of steps and bit-identical outputs at every step (first difference named)."""
    assert len(ref) == len(got), f"{what}: {len(ref)} vs {len(got)} steps"
    for t, (x, y) in enumerate(zip(ref, got, strict=True)):
        diffs = bit_differences(x, y)
        assert not diffs, f"{what}: step {t} differs at {diffs}"


def runs_differ(a: list[TensorDict], b: list[TensorDict]) -> bool:
    return any(bit_differences(x, y) for x, y in zip(a, b, strict=True))


# ---------------------------------------------------------------------- worker factories
def make_env_after_intersection(scenario: str, **kwargs):
    """A ParallelEnv worker factory (module level: picklable) whose process creates and
    steps intersection-v0 before building the env, and resets it once more afterwards:
    intersection-v0 overwrites IDMVehicle's constants for the whole process."""
    import gymnasium as gym

    from torchrl_grpo.envs import HighwayEnv

    crossing = gym.make("intersection-v0")
    crossing.reset(seed=0)
    crossing.step(1)
    env = HighwayEnv(scenario, **kwargs)
    crossing.reset(seed=1)
    return env


def assert_branches_match_highway_env(scenario: str, action: int, horizon: int) -> None:
    """``branch_rollout`` of 2 roots x 2 branches of a constant action on the tensor
    simulator (float64, roots imported from highway-env) gives highway-env's masks and
    rewards (to HighwayEnv's float32)."""
    from torchrl_grpo.branching import MASK, branch_rollout, make_roots, reset_roots
    from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv

    highway_roots = reset_roots(HighwayEnv(scenario), 2, seed=3)

    def policy(td):
        return td.set("action", torch.full(td.batch_size, action, dtype=torch.int64))

    highway = branch_rollout(HighwayEnv(scenario), policy, highway_roots, 2, horizon)
    env = TensorHighwayEnv(scenario, num_envs=4, dtype=torch.float64)
    roots = make_roots(env.state_from_highway(highway_roots["state"]))
    tensor = branch_rollout(env, policy, roots, 2, horizon)
    assert torch.equal(tensor[MASK], highway[MASK])
    mask = highway[MASK]
    a, b = tensor["next", "reward"][mask].double(), highway["next", "reward"][mask].double()
    assert torch.allclose(a, b, atol=1e-6)


def visited_states(scenario: str, n_actions: int, episodes: int = 3, steps: int = 10):
    """HighwayEnv states along episodes of random actions (seeded), the final ones included."""
    import numpy as np

    from torchrl_grpo.envs import HighwayEnv

    env = HighwayEnv(scenario, seed=0)
    rng = np.random.default_rng(0)
    states = []
    for _ in range(episodes):
        env.reset()
        for _ in range(steps):
            states.append(env.get_state())
            td = env.step(TensorDict(action=torch.tensor(int(rng.integers(n_actions)))))
            if bool(td["next", "done"]):
                states.append(env.get_state())
                break
    return torch.stack(states)


def replayed_twice(env, steps: int, seed: int = 0) -> list:
    """Two plays of the same random actions from one restored root: (outputs, final state).

    The batched env's ``step_and_maybe_reset`` runs ``steps`` steps (episodes end and
    rows reset) from ``env.get_state()`` twice; a deterministic step gives equal plays.
    """
    batch = env.batch_size[0]
    g = torch.Generator().manual_seed(seed)
    actions = [torch.randint(0, 5, (batch,), generator=g) for _ in range(steps)]
    root = env.get_state()
    plays = []
    for _ in range(2):
        td = env.reset(TensorDict(state=root, batch_size=[batch]), set_state=True)
        play = []
        for action in actions:
            td.set("action", action)
            out, td = env.step_and_maybe_reset(td)
            play.append(out["next"].exclude("state"))
        plays.append((torch.stack(play), env.get_state()))
    return plays


def stepped_states(scenario: str, dtype, steps: int, batch: int = 32) -> list:
    """The tensor step's states after each of ``steps`` random steps (finished rows reset)."""
    env = TensorHighwayEnv(scenario, num_envs=batch, seed=5, dtype=dtype)
    g = torch.Generator().manual_seed(2)
    td = env.reset()
    states = []
    for _ in range(steps):
        td.set("action", torch.randint(0, env.action_spec.space.n, (batch,), generator=g))
        _, td = env.step_and_maybe_reset(td)
        states.append(env.get_state())
    return states
