import logging

import pytest
import torch
from modules_helpers import LAYOUT, scene
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_grpo.modules import (
    META_ACTIONS,
    SCRIPTED_POLICIES,
    ConstantActionPolicy,
    KinematicsLayout,
    RandomPolicy,
    RulePolicy,
    make_scripted_policy,
)
from torchrl_grpo.modules.scripted.actions import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, SLOWER
from torchrl_grpo.modules.scripted.policies import (
    AggressivePolicy,
    CautiousPolicy,
    ConservativePolicy,
    LaneChangePolicy,
)


def act(policy: TensorDictModule, obs: torch.Tensor) -> int:
    return policy(TensorDict(observation=obs, batch_size=obs.shape[:-2]))["action"].item()


def test_action_indices_match_highway_env():
    from highway_env.envs.common.action import DiscreteMetaAction

    assert {v: k for k, v in DiscreteMetaAction.ACTIONS_ALL.items()} == META_ACTIONS


def test_constant_and_random_are_batch_capable():
    td = TensorDict(observation=torch.zeros(2, 3, 4, 5, 5), batch_size=[2, 3, 4])
    for name, value in [("IDLE", IDLE), ("SLOWER", SLOWER), (FASTER, FASTER)]:
        out = ConstantActionPolicy(name)(td.clone())["action"]
        assert out.shape == (2, 3, 4) and out.dtype == torch.int64 and (out == value).all()
    with pytest.raises(ValueError):
        ConstantActionPolicy("BRAKE")  # type: ignore[arg-type]
    a = RandomPolicy(5, seed=3)(td.clone())["action"]
    b = RandomPolicy(5, seed=3)(td.clone())["action"]
    c = RandomPolicy(5, seed=4)(td.clone())["action"]
    assert a.shape == (2, 3, 4) and a.dtype == torch.int64
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.min() >= 0 and a.max() < 5


def test_policies_are_tensordict_modules():
    for name in SCRIPTED_POLICIES:
        policy = make_scripted_policy(name, LAYOUT)
        assert isinstance(policy, TensorDictModule)
        assert policy.in_keys == ["observation"] and policy.out_keys == ["action"]
    with pytest.raises(KeyError):
        make_scripted_policy("kamikaze")


def test_layout_round_trip_and_highway_defaults():
    import gymnasium as gym
    import highway_env  # noqa: F401
    from highway_env.road.lane import AbstractLane
    from highway_env.vehicle.kinematics import Vehicle

    from torchrl_grpo.modules.kinematics_table import LANE_WIDTH, MAX_SPEED, VEHICLE_LENGTH

    assert (MAX_SPEED, LANE_WIDTH, VEHICLE_LENGTH) == (
        Vehicle.MAX_SPEED,
        AbstractLane.DEFAULT_WIDTH,
        Vehicle.LENGTH,
    )
    env = gym.make("highway-fast-v0")
    obs, _ = env.reset(seed=0)
    layout = KinematicsLayout.from_highway_config(env.unwrapped.config)
    obs_type = env.unwrapped.observation_type
    assert layout._ranges == {k: tuple(v) for k, v in obs_type.features_range.items()}
    cols = layout.decode(torch.as_tensor(obs))
    ego = env.unwrapped.vehicle
    assert cols["y"][0].item() == pytest.approx(ego.position[1], abs=1e-4)
    assert cols["vx"][0].item() == pytest.approx(ego.velocity[0], abs=1e-3)
    torch.testing.assert_close(layout.encode(cols), torch.as_tensor(obs))
    env.close()


def test_layout_absolute_and_unnormalised():
    layout = KinematicsLayout(normalize=False, absolute=True)
    obs = torch.tensor([[1.0, 100.0, 4.0, 25.0, 0.0], [1.0, 120.0, 8.0, 20.0, 0.0]])
    cols = layout.decode(obs)
    assert cols["x"].tolist() == [100.0, 20.0] and cols["y"].tolist() == [4.0, 4.0]
    torch.testing.assert_close(layout.encode(cols), obs)
    with pytest.raises(ValueError, match="Kinematics"):
        KinematicsLayout.from_highway_config({"observation": {"type": "OccupancyGrid"}})
    with pytest.raises(ValueError, match="needed"):
        RulePolicy(KinematicsLayout(features=("presence", "x", "y")))


def test_rule_policy_does_not_go_faster_with_a_car_close_ahead():
    rule = RulePolicy(LAYOUT)
    for lane in range(3):
        for dvx in (-5.0, 0.0, 3.0):
            action = act(rule, scene(lane, 25.0, [(12.0, 0, dvx)]))
            assert action != FASTER, (lane, dvx)


def test_rule_policy_brakes_when_boxed_in():
    rule = RulePolicy(LAYOUT)
    # Middle lane, slow car 12 m ahead, cars beside on both sides.
    obs = scene(1, 25.0, [(12.0, 0, -5.0), (0.0, -1, 0.0), (1.0, 1, 0.0)])
    assert act(rule, obs) == SLOWER


def test_rule_policy_escapes_into_a_clear_lane():
    rule = RulePolicy(LAYOUT)
    # Left lane blocked ahead, right neighbour lane empty: move right rather than brake.
    assert act(rule, scene(0, 25.0, [(15.0, 0, -5.0)])) == LANE_RIGHT
    # Rightmost lane blocked ahead, left lane empty: overtake on the left.
    assert act(rule, scene(2, 25.0, [(15.0, 0, -5.0)])) == LANE_LEFT


def test_rule_policy_accelerates_on_a_free_road_in_the_right_lane():
    rule = RulePolicy(LAYOUT)
    assert act(rule, scene(2, 25.0)) == FASTER
    assert act(rule, scene(2, 25.0, [(150.0, 0, 0.0), (20.0, -1, 0.0)])) == FASTER


def test_rule_policy_keeps_right_when_free():
    rule = RulePolicy(LAYOUT)
    assert act(rule, scene(0, 25.0)) == LANE_RIGHT
    assert act(RulePolicy(LAYOUT, prefer_right=False), scene(0, 25.0)) == FASTER


def test_rule_policy_does_not_cut_in_front_of_a_fast_follower():
    rule = RulePolicy(LAYOUT)
    # Right lane: a car 8 m behind, 10 m/s faster. Moving there would be hit.
    assert act(rule, scene(1, 25.0, [(-8.0, 1, 10.0)])) != LANE_RIGHT
    # Same car but slower than the ego: safe to move right.
    assert act(rule, scene(1, 25.0, [(-12.0, 1, -3.0)])) == LANE_RIGHT


def test_rule_policy_is_batch_capable_and_matches_single_calls():
    rule = RulePolicy(LAYOUT)
    scenes = [
        scene(1, 25.0, [(12.0, 0, -5.0), (0.0, -1, 0.0), (1.0, 1, 0.0)]),
        scene(0, 25.0, [(15.0, 0, -5.0)]),
        scene(2, 25.0),
        scene(0, 30.0, [(40.0, 0, -2.0), (-3.0, 1, 0.0)]),
    ]
    batch = torch.stack(scenes).reshape(2, 2, 5, 5)
    actions = rule(TensorDict(observation=batch, batch_size=[2, 2]))["action"]
    assert actions.shape == (2, 2)
    assert actions.flatten().tolist() == [act(rule, s) for s in scenes]


def test_branch_policies():
    near_ahead = scene(1, 25.0, [(12.0, 0, -3.0)])
    free = scene(1, 25.0)
    # aggressive: full speed, overtakes (left first) when blocked.
    aggressive = AggressivePolicy(LAYOUT)
    assert act(aggressive, free) == FASTER
    assert act(aggressive, near_ahead) == LANE_LEFT
    # conservative: keeps a long distance, never changes lane.
    conservative = ConservativePolicy(LAYOUT)
    assert act(conservative, free) == IDLE
    assert act(conservative, scene(1, 25.0, [(60.0, 0, 0.0)])) == SLOWER
    assert act(conservative, near_ahead) == SLOWER
    # left / right: change lane when clear, then keep the lane.
    left, right = LaneChangePolicy("left", LAYOUT), LaneChangePolicy("right", LAYOUT)
    assert act(left, free) == LANE_LEFT
    assert act(right, free) == LANE_RIGHT
    assert act(left, scene(0, 25.0)) == IDLE
    assert act(right, scene(2, 25.0)) == IDLE
    assert act(left, scene(1, 25.0, [(2.0, -1, 0.0)])) == IDLE  # left lane occupied
    assert act(left, scene(0, 25.0, [(10.0, 0, -2.0)])) == SLOWER
    # cautious: keeps speed, slows when anything is near (any lane), not for cars behind.
    cautious = CautiousPolicy(LAYOUT)
    assert act(cautious, free) == IDLE
    assert act(cautious, scene(1, 25.0, [(15.0, 1, 0.0)])) == SLOWER
    assert act(cautious, scene(1, 25.0, [(-20.0, 0, 0.0)])) == IDLE
    with pytest.raises(ValueError):
        LaneChangePolicy("up", LAYOUT)  # type: ignore[arg-type]


def test_absent_vehicles_are_ignored_by_rule_policy():
    rule = RulePolicy(LAYOUT)
    obs = scene(2, 25.0)
    # An absent row with a "car" 5 m ahead in its features must not matter.
    obs[1, 1:] = LAYOUT.encode(
        {
            "presence": torch.zeros(5),
            "x": torch.full((5,), 5.0),
            "y": torch.zeros(5),
            "vx": torch.zeros(5),
            "vy": torch.zeros(5),
        }
    )[1, 1:]
    assert act(rule, obs) == FASTER


def test_scripted_policies_drive_the_gym_env():
    import highway_env  # noqa: F401
    from torchrl.envs import GymEnv

    env = GymEnv("highway-fast-v0", categorical_action_encoding=True)
    layout = KinematicsLayout.from_highway_config(env.unwrapped.config)
    td = env.rollout(5, policy=RulePolicy(layout), auto_reset=False, tensordict=env.reset(seed=0))
    assert td["action"].dtype == torch.int64
    env.close()


@pytest.mark.slow
def test_rule_policy_beats_always_slower_on_highway_fast():
    """Ten episodes (seeds 0-9) each: higher mean return, no crash."""
    import highway_env  # noqa: F401
    from torchrl.envs import GymEnv

    env = GymEnv("highway-fast-v0", categorical_action_encoding=True)
    layout = KinematicsLayout.from_highway_config(env.unwrapped.config)
    results = {}
    for name in ("slower", "rule"):
        policy = make_scripted_policy(name, layout)
        returns, crashes = [], 0
        for seed in range(10):
            td = env.rollout(
                100,
                policy=policy,
                auto_reset=False,
                tensordict=env.reset(seed=seed),
                break_when_any_done=True,
            )
            returns.append(td["next", "reward"].sum().item())
            crashes += int(td["next", "terminated"][-1].item())
        results[name] = (sum(returns) / len(returns), crashes)
        logging.getLogger(__name__).info("%s: %s", name, results[name])
    assert results["rule"][0] > results["slower"][0]
    assert results["rule"][1] == 0
    env.close()
