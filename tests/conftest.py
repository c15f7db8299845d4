"""Shared by every test: conf/ holds the experimental algorithm's files (algo=grpo_lab).

Under pytest-xdist (``-n``, the default in pyproject.toml) each worker takes its share of
the cores for torch's threads, so two workers on 2 cores do not run four threads.
"""

import os

import torch

import torchrl_grpo.experimental  # noqa: F401  (registers algo=grpo_lab, model=lab)

if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    torch.set_num_threads(max(1, (_cores or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))
