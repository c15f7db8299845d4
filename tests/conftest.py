"""Shared by every test: conf/ holds the experimental algorithm's files (algo=grpo_lab)."""

import torchrl_grpo.experimental  # noqa: F401  (registers algo=grpo_lab, model=lab)
