"""Fixtures of the branching tests (helpers live in ``branching_helpers``)."""

from __future__ import annotations

import multiprocessing
import time

import pytest
import torch
from branching_helpers import branch_env

from torchrl_grpo.branching import shutdown_env


@pytest.fixture
def no_workers_left():
    """Asserts, after the test, that no worker process it started is still alive."""
    before = {p.pid for p in multiprocessing.active_children()}
    yield
    alive = [p for p in multiprocessing.active_children() if p.pid not in before]
    # A worker told to stop may still be exiting on a loaded machine: give it seconds.
    deadline = time.monotonic() + 10
    while alive and time.monotonic() < deadline:
        alive[0].join(0.1)
        alive = [p for p in alive if p.is_alive()]
    assert not alive, f"worker processes left behind: {alive}"


@pytest.fixture(scope="session")
def highway_parallel():
    """One 2-worker ParallelEnv of highway-fast-v0 shared by the tests that only read it."""
    env = branch_env("highway-fast-v0", "parallel")
    yield env
    shutdown_env(env)


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)
