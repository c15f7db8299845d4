"""bench_scenario_room: its rows against hand-computed figures, and one short run."""

import subprocess
import sys
from pathlib import Path

import bench_scenario_room as bench
import pytest

from torchrl_grpo.training.results import EvalResult

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.experimental


def _bench(*args: str) -> str:
    """The script's standard output for ``args``."""
    script = str(ROOT / "benchmarks/lab/bench_scenario_room.py")
    run = subprocess.run(
        [sys.executable, script, *args], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return run.stdout


def _result(name, returns, crashed):
    n = len(returns)
    return EvalResult(name, returns, crashed, [11] * n, [4.0] * n, list(range(n)))


def test_a_row_pairs_with_always_slower_by_hand():
    slower = _result("always-SLOWER", [9.0, 9.0, 9.0], [False] * 3)
    search = _result("search", [10.0, 11.0, 12.0], [False] * 3)
    # Differences 1, 2, 3: mean 2, standard deviation 1, standard error 1 / sqrt(3).
    row = bench.table_row(search, slower, seconds=90.0)
    # No crash of always-SLOWER: all 2.00 from the others, whose 5th percentile is
    # 1 + 0.1 * (2 - 1) = 1.10 (numpy's linear interpolation between 1 and 2).
    assert row == (
        "| search | 11.00 ± 0.58 | 0.0% | 4.0 | +2.00 ± 0.58, beats always-SLOWER "
        "| +0.00 / +2.00 (+1.10) | 1.5 |"
    )
    crashing = _result("crashing", [10.0, 11.0, 12.0], [True, False, False])
    assert bench.table_row(crashing, slower, seconds=0.0).endswith(
        "+2.00 ± 0.58, does not beat always-SLOWER | +0.00 / +2.00 (+1.10) | 0.0 |"
    )
    # always-SLOWER crashes in the first episode: 1 of the 6 there, 5 in the others.
    slower_crash = _result("always-SLOWER", [9.0, 9.0, 9.0], [True, False, False])
    assert "| +0.33 / +1.67 (+2.05) |" in bench.table_row(search, slower_crash, seconds=0.0)


@pytest.mark.slow  # 26 and 34 s, a lab script's whole runs: the default suite's 10 minutes
@pytest.mark.parametrize(
    ("on", "other", "bases"),
    [("highway", "float32", ["slower"]), ("tensor", "float64", ["idle", "slower"])],
)
def test_a_short_run_prints_every_policy_row(on, other, bases):
    out = _bench(
        *("--scenario", "roundabout-v0", "--bases", *bases, "--horizons", "2"),
        *("--episodes", "2", "--workers", "1", "--on", on),
        *("--dtypes", "float64", "float32"),
    )
    assert out.startswith(
        f"roundabout-v0: 2 {'highway-env' if on == 'highway' else 'tensor-simulator'}"
    )
    rows = [line for line in out.splitlines() if line.startswith("| ")]
    # The dtype is named where it is not the default for where the episodes run.
    names = [r.split(" | ")[0] for r in rows[1:]]
    labels = {"slower": "always-SLOWER", "idle": "always-IDLE"}
    expected = []
    for base in bases:
        label = labels[base]
        # One search row per --dtypes entry, in its order (float64, float32).
        searches = [f"| search 2 over {label}", f"| search 2 over {label}, {other}"]
        expected += [f"| {label}", *(searches if on == "highway" else searches[::-1])]
    assert names == expected
    # always-SLOWER against itself, wherever its row is: no difference, and not a win.
    own = rows[1 + names.index("| always-SLOWER")]
    assert "+0.00 ± 0.00, does not beat always-SLOWER" in own


@pytest.mark.slow  # 31 s: the default suite's 10-minute budget
def test_trained_runs_are_driven_with_their_own_config(tmp_path):
    # A run trained with merge-v0's x range widened: every row of the table, always-SLOWER
    # included, is driven with that observation (the run's policy would refuse another).
    from torchrl_grpo.training import compose_config, make_env
    from torchrl_grpo.training.checkpoint import save_checkpoint
    from torchrl_grpo.training.config import to_container
    from torchrl_grpo.training.model_builder import make_policy

    ranges = "{x:[-400,400],y:[-8,8],vx:[-80,80],vy:[-80,80]}"
    cfg = compose_config(
        [
            "experiment=smoke",
            "env=merge",
            "model=mlp",
            f"+env.config.observation={{type:Kinematics,features_range:{ranges}}}",
        ]
    )
    policy = make_policy(cfg.model, make_env(cfg.env, seed=0))
    path = save_checkpoint(
        {"config": to_container(cfg), "policy": policy.state_dict()}, tmp_path / "run" / "last.pt"
    )
    out = _bench(
        *("--scenario", "merge-v0", "--bases", "slower", "--horizons"),
        *("--episodes", "2", "--workers", "1", "--on", "tensor", "--checkpoints", str(path)),
    )
    names = [line.split(" | ")[0] for line in out.splitlines() if line.startswith("| ")]
    assert names[1:] == ["| always-SLOWER", "| run"]
