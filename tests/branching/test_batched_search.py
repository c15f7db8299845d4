"""search_episodes: all episodes planned at once play what the one-state planner plays.

The reference is today's planner, :class:`LookaheadPolicy` deciding one state at a time
(one rollout of five rows per decision), driving the evaluation's episodes through the
evaluation's own code (``play_episode`` on highway-env, ``tensor_episodes`` on the
tensor simulator). The batched planner must give the same actions and the
same returns, episode for episode.
"""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from torchrl_grpo.branching import LookaheadPolicy
from torchrl_grpo.branching.batched_search import highway_starts, search_episodes
from torchrl_grpo.envs import HighwayEnv, TensorHighwayEnv, states_equal
from torchrl_grpo.modules import make_scripted_policy
from torchrl_grpo.training.eval_episodes import play_episode
from torchrl_grpo.training.transfer import tensor_episodes

SCENARIO = "highway-fast-v0"
SEEDS = [10_000, 10_001, 10_002]
HORIZON = 2
STEPS = 6


def _compare(reference: list, out) -> None:
    """Each episode's actions equal, its return within 1e-5, its length equal."""
    for i, data in enumerate(reference):
        played = out["mask"][i]
        assert int(played.sum()) == data.shape[-1]
        assert out["action"][i][played].tolist() == data["action"].reshape(-1).tolist()
        ret = float(out["reward"][i][played].sum())
        assert ret == pytest.approx(float(data["next", "reward"].sum()), abs=1e-5)
        assert not bool(out["mask"][i][data.shape[-1] :].any())


def test_batched_search_on_the_tensor_simulator_plays_the_one_state_planners_episodes():
    rule = make_scripted_policy("rule")
    # Today's planner on the tensor simulator: the evaluation's episodes as rows, each
    # row's decision one rollout of its 5 branches (a planning env of 5 rows).
    old = LookaheadPolicy(TensorHighwayEnv(SCENARIO, num_envs=5), rule, HORIZON)
    cfg = OmegaConf.create({"scenario": SCENARIO, "config": {}, "max_episode_steps": STEPS})
    data, steps = tensor_episodes(cfg, old, episodes=len(SEEDS), seed=SEEDS[0], return_state=True)
    reference = [data[i][steps[i]] for i in range(len(SEEDS))]
    plan = TensorHighwayEnv(SCENARIO, num_envs=5 * len(SEEDS))
    new = LookaheadPolicy(plan, rule, HORIZON)
    worlds = TensorHighwayEnv(SCENARIO, num_envs=len(SEEDS), return_state=True)
    out = search_episodes(new, worlds, SEEDS, STEPS)
    _compare(reference, out)
    # The same branches were simulated, all episodes' in one rollout per step.
    assert new.frames == old.frames
    assert plan.world_steps == 5 * len(SEEDS) * HORIZON * STEPS
    # The controls: the search is not the base policy's constant choice, and the
    # episodes differ from one another.
    actions = out["action"][out["mask"]]
    assert len(set(actions.tolist())) > 1
    assert len({tuple(a.tolist()) for a in out["action"]}) == len(SEEDS)


def test_batched_search_on_highway_env_imports_all_episodes_states_in_one_call():
    rule = make_scripted_policy("rule")
    sim = TensorHighwayEnv(SCENARIO, num_envs=5)
    old = LookaheadPolicy(sim, rule, HORIZON, import_state=sim.state_from_highway)
    driven = HighwayEnv(SCENARIO, return_state=True)
    seeds, steps = SEEDS[:2], 6
    reference = [play_episode(driven, old, seed, steps) for seed in seeds]
    plan = TensorHighwayEnv(SCENARIO, num_envs=5 * len(seeds))
    calls = []

    def counted(states):
        calls.append(states.shape[0])
        return plan.state_from_highway(states)

    new = LookaheadPolicy(plan, rule, HORIZON, import_state=counted)
    lanes = [HighwayEnv(SCENARIO, return_state=True) for _ in seeds]
    out = search_episodes(new, lanes, seeds, steps)
    _compare(reference, out)
    assert calls == [len(seeds)] * steps  # one bridge call of all live states per step


def test_an_ended_episode_drops_out_of_the_planning():
    # Episodes of 3 steps (duration 3) in a cap of 5: nothing is planned after the end.
    rule = make_scripted_policy("rule")
    plan = TensorHighwayEnv(SCENARIO, {"duration": 3}, num_envs=10)
    planner = LookaheadPolicy(plan, rule, HORIZON)
    worlds = TensorHighwayEnv(SCENARIO, {"duration": 3}, num_envs=2, return_state=True)
    out = search_episodes(planner, worlds, [0, 1], max_steps=5)
    assert out["mask"].sum(-1).tolist() == [3, 3]
    assert (out["action"][:, 3:] == -1).all()
    # Two full branches from steps 0 and 1; from step 2 every branch ends after one step.
    assert plan.world_steps == 10 * (HORIZON + HORIZON + 1)


def test_the_tensor_episodes_start_where_highway_envs_episodes_start():
    # In float64 the bridge is exact: the imported starts, exported back, are bitwise
    # highway-env's own episode starts.
    sim = TensorHighwayEnv(SCENARIO, num_envs=3, dtype=torch.float64)
    starts = highway_starts(sim, [5, 6, 7])
    highway = HighwayEnv(SCENARIO)
    for i, seed in enumerate([5, 6, 7]):
        highway.set_seed(seed)
        highway.reset()
        assert states_equal(sim.state_to_highway(starts["state"])[i], highway.get_state())
    assert not torch.equal(starts["observation"][0], starts["observation"][1])


def test_refusals_name_the_problem():
    rule = make_scripted_policy("rule")
    on_highway = LookaheadPolicy(HighwayEnv(SCENARIO), rule, HORIZON)
    worlds = TensorHighwayEnv(SCENARIO, num_envs=1, return_state=True)
    with pytest.raises(ValueError, match="batched simulator"):
        search_episodes(on_highway, worlds, [0], 2)
    planner = LookaheadPolicy(TensorHighwayEnv(SCENARIO, num_envs=5), rule, HORIZON)
    with pytest.raises(ValueError, match="return_state=True"):
        search_episodes(planner, TensorHighwayEnv(SCENARIO, num_envs=1), [0], 2)
    with pytest.raises(ValueError, match="2 seeds need as many envs"):
        search_episodes(planner, [HighwayEnv(SCENARIO, return_state=True)], [0, 1], 2)
    with pytest.raises(ValueError, match="tensor simulator of 2 worlds"):
        search_episodes(planner, worlds, [0, 1], 2)
