"""Helpers of the branching tests: scripted per-branch actions, envs, comparisons.

ParallelEnv workers are started with ``fork`` here: it starts in well under a second
(``spawn`` re-imports torch in every worker, 10+ s on 2 cores) and the workers are
CPU-only. One test checks the default start method.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

import torch
from tensordict import TensorDictBase
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.branching import make_branch_env
from torchrl_grpo.envs import HighwayEnv
from torchrl_grpo.modules import KinematicsMLP, make_discrete_actor

# highway-env flags its older scenario versions as out of date on every gym.make.
warnings.filterwarnings("ignore", message=".*is out of date.*")

SCENARIOS = ("highway-fast-v0", "merge-v0", "intersection-v0")
# Short episodes, so that branches end inside small horizons.
SHORT = {
    "highway-fast-v0": {"duration": 4},
    "merge-v0": {},
    "intersection-v0": {"duration": 2},
}

# DiscreteMetaAction indices; intersection-v0 only has the longitudinal actions.
_META = {"LANE_LEFT": 0, "IDLE": 1, "LANE_RIGHT": 2, "FASTER": 3, "SLOWER": 4}
_LONGITUDINAL = {"SLOWER": 0, "IDLE": 1, "FASTER": 2}
N_ACTIONS = {"highway-fast-v0": 5, "merge-v0": 5, "intersection-v0": 3}


def actions(scenario: str, *rows: list[str]) -> torch.Tensor:
    """A ``[G, T]`` action table from action names; lane changes become IDLE where absent."""
    names = _LONGITUDINAL if N_ACTIONS[scenario] == 3 else _META
    return torch.tensor([[names.get(a, 1) for a in row] for row in rows])


def mixed_actions(scenario: str) -> torch.Tensor:
    """A ``[5, 6]`` table of five branches that speed up, weave, idle, turn and brake."""
    return actions(
        scenario,
        ["FASTER"] * 6,
        ["LANE_LEFT", "SLOWER"] * 3,
        ["IDLE"] * 6,
        ["LANE_RIGHT", "FASTER"] * 3,
        ["SLOWER"] * 6,
    )


def mlp_actor(scenario: str) -> ProbabilisticActor:
    """A categorical MLP actor over ``scenario``'s observation, five actions."""
    obs = plain_env(scenario).observation_spec["observation"].shape
    return make_discrete_actor(KinematicsMLP(obs[-2], obs[-1], out_features=5), 5)


def plain_env(scenario: str, **kwargs) -> HighwayEnv:
    """A plain HighwayEnv (its default padding is the one branch workers use)."""
    return HighwayEnv(scenario, **kwargs)


def branch_env(scenario: str, backend: str, num_workers: int = 2, **kwargs):
    """An env of ``backend`` ("parallel" with fork, "serial", "single")."""
    if backend == "single":
        num_workers = 1
    extra = {"mp_start_method": "fork"} if backend == "parallel" else {}
    return make_branch_env(scenario, num_workers, backend=backend, **extra, **kwargs)


@contextlib.contextmanager
def engine(env, *, whole: bool = False) -> Iterator[None]:
    """Run ``env``'s branch rollouts with one engine: whole branches in the workers
    (``whole=True``), else lock-step with the policy in this process."""
    env.whole_branches = whole
    try:
        yield
    finally:
        del env.whole_branches


class ScheduledPolicy:
    """Plays ``table[branch, t]`` (t = steps since the root), whatever it observes.

    It reads the ``branch``, ``step_count`` and ``root_step`` entries the branch
    engine writes for the policy, so the actions of a branch do not depend on the
    slot (worker) or wave it runs in.
    """

    def __init__(self, table: torch.Tensor) -> None:
        self.table = torch.as_tensor(table, dtype=torch.long)
        self.calls = 0

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        self.calls += 1
        t = (td["step_count"].squeeze(-1) - td["root_step"]).clamp(max=self.table.shape[1] - 1)
        g = td["branch"].clamp(max=self.table.shape[0] - 1)
        td["action"] = self.table[g, t]
        return td


def bitwise_equal(a: TensorDictBase, b: TensorDictBase) -> list[str]:
    """Keys at which two tensordicts differ in keys, dtype, shape or bytes."""
    keys_a, keys_b = set(a.keys(True, True)), set(b.keys(True, True))
    diffs = [str(k) for k in keys_a ^ keys_b]
    for key in keys_a & keys_b:
        x, y = a.get(key), b.get(key)
        if x.dtype != y.dtype or x.shape != y.shape:
            diffs.append(str(key))
            continue
        if x.dtype.is_floating_point:
            x = x.contiguous().reshape(-1).view(torch.uint8)
            y = y.contiguous().reshape(-1).view(torch.uint8)
        if not torch.equal(x, y):
            diffs.append(str(key))
    return sorted(diffs)
