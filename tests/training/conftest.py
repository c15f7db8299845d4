"""Fixtures of the training tests: a shared smoke run, the seed (helpers in train_setup.py)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import torch
from train_setup import run_script


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path, float]:
    """One smoke training run in a subprocess (CSV logger), shared by the tests reading it."""
    import time

    run_dir = tmp_path_factory.mktemp("smoke") / "run"
    start = time.monotonic()
    proc = run_script(
        "train.py",
        [
            "experiment=smoke",
            "logger=csv",
            "algo.kl_to_ref_coeff=0.01",
            f"experiment.out_dir={run_dir}",
        ],
    )
    return proc, run_dir, time.monotonic() - start


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)
