"""Evaluation on forked workers: the serial table, episode for episode, and clear errors."""

from __future__ import annotations

import json
import os

import pytest
import torch
from train_setup import compose_config

from torchrl_grpo.modules import ConstantActionPolicy, make_scripted_policy
from torchrl_grpo.training import evaluate, make_env, make_policy
from torchrl_grpo.training.checkpoint import get_rng_state
from torchrl_grpo.training.eval_episodes import eval_workers
from torchrl_grpo.training.evaluation import evaluate_checkpoint


def _per_episode(result):
    columns = (result.seeds, result.returns, result.crashed, result.lengths, result.speeds)
    return list(zip(*columns, strict=True))


def test_two_workers_give_the_serial_results_episode_for_episode():
    cfg = compose_config(["experiment=smoke", "env.max_episode_steps=8"])
    env = make_env(cfg.env, seed=0)
    policy = make_policy(cfg.model, env)  # untrained: it changes lanes, crashes, stops early
    runs = {}
    for workers in (1, 2):
        before = get_rng_state()
        runs[workers], _ = evaluate(
            env, policy, episodes=4, seed=20_000, max_steps=8, workers=workers
        )
        # The caller's random streams are not drawn from: a run trains the same either way.
        after = get_rng_state()
        assert torch.equal(before["torch"], after["torch"])
        assert str(before["numpy"]) == str(after["numpy"]) and before["python"] == after["python"]
    assert runs[2].seeds == [20_000, 20_001, 20_002, 20_003]
    assert _per_episode(runs[1]) == _per_episode(runs[2])


def test_a_policy_with_its_own_generator_draws_as_in_one_process():
    # Its draws run on from one episode to the next: copies in workers would repeat them.
    env = make_env(compose_config(["experiment=smoke"]).env)
    results = [
        evaluate(
            env,
            make_scripted_policy("random", n_actions=5, seed=3),
            episodes=3,
            seed=0,
            max_steps=6,
            workers=workers,
        )[0]
        for workers in (1, 2)
    ]
    assert _per_episode(results[0]) == _per_episode(results[1])


def test_evaluate_py_tables_with_one_and_two_workers_are_identical(tmp_path):
    tables = []
    for workers in (1, 2):
        cfg = compose_config(
            [
                "env=highway_fast",
                "env.max_episode_steps=6",
                "episodes=3",
                "seed=7",
                "baselines=[idle,slower]",
                "video=false",
                f"eval_workers={workers}",
            ],
            config_name="evaluate",
        )
        evaluate_checkpoint(cfg, tmp_path / str(workers))
        tables.append(json.loads((tmp_path / str(workers) / "results.json").read_text()))
    assert tables[0] == tables[1] and len(tables[0]) == 2


class _FailsInWorkers(ConstantActionPolicy):
    """IDLE here; in a worker process, ``ValueError`` (or the worker dies)."""

    def __init__(self, die: bool = False) -> None:
        super().__init__("IDLE")
        self.parent, self.die = os.getpid(), die

    def forward(self, td):
        if os.getpid() != self.parent:
            if self.die:
                os._exit(3)
            raise ValueError("a policy bug")
        return super().forward(td)


def test_an_error_in_a_worker_surfaces_here_with_its_episode_and_the_env_stays_usable():
    env = make_env(compose_config(["experiment=smoke"]).env)
    with pytest.raises(
        RuntimeError,
        match=r"episode \d \(seed 1\d\) failed in a worker process: "
        r"ValueError: a policy bug",
    ) as err:
        evaluate(env, _FailsInWorkers(), episodes=3, seed=10, max_steps=4, workers=2)
    assert "a policy bug" in str(err.value.__cause__.__cause__)  # the worker's traceback
    with pytest.raises(RuntimeError, match="a worker process died"):
        evaluate(env, _FailsInWorkers(die=True), episodes=3, seed=10, max_steps=4, workers=2)
    res, _ = evaluate(env, _FailsInWorkers(), episodes=2, seed=10, max_steps=4, workers=1)
    assert res.lengths == [4, 4]


def test_eval_workers_defaults_to_the_usable_cores_and_refuses_zero():
    assert eval_workers(None) == len(os.sched_getaffinity(0))
    assert eval_workers(2) == 2
    with pytest.raises(ValueError, match="eval_workers must be >= 1"):
        eval_workers(0)
    cfg = compose_config(["experiment=smoke"])
    assert cfg.experiment.eval_workers is None
