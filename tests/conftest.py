"""Shared by every test: conf/ holds the experimental algorithm's files (algo=grpo_lab).

Under pytest-xdist (``-n auto``, the default in pyproject.toml) each worker takes its
share of the cores for its threads, and so does every process a test starts (env
workers, scripts): it is set in the environment before torch loads. Two workers on 2
cores with two spinning OpenMP threads each ran some tests 10 times slower.
"""

import os

if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    _threads = max(1, (_cores or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    os.environ.setdefault("OMP_NUM_THREADS", str(_threads))
    os.environ.setdefault("MKL_NUM_THREADS", str(_threads))

import torch  # noqa: E402

import torchrl_grpo.experimental  # noqa: E402, F401  (registers algo=grpo_lab, model=lab)

if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
