"""Every tutorial in tutorials/ runs in its short form and draws the pictures it promises.

Each tutorial runs as a user would run it, ``python tutorials/<name>.py --quick --out
DIR``, in a fresh interpreter (its vehicle-class registrations and Hydra state stay
there). The test checks its exit code, the lines it prints with its results, and that
every picture it promises is a real image (not a blank canvas). A tutorial without an
entry in ``EXPECTED`` is still run, and must write at least one picture; one with a
test file of its own (``OWN_TESTS``) is left to it.

The selected tutorials run two at a time (one per core of a small machine), started
when the first of these tests asks: each takes 8 to 15 s, about 5 s of it imports.
"""

import os
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = sorted(p.stem for p in (ROOT / "tutorials").glob("*.py") if p.stem != "__init__")
# Tutorials with a test file of their own, which runs them: not run a second time here.
OWN_TESTS = {"cartpole_grpo": ROOT / "tests" / "test_tutorial_cartpole.py"}
RUN_HERE = [name for name in TUTORIALS if not (name in OWN_TESTS and OWN_TESTS[name].exists())]

# name: (pictures written into --out, regular expressions the printed output must match)
EXPECTED: dict[str, tuple[list[str], list[str]]] = {
    "branch_scripted_policies": (
        [
            "rewards_over_time.png",
            "trajectories.png",
            "reward_distribution.png",
            "distance_vs_return.png",
            "group.png",
        ],
        [
            r"all 5 branches started from bitwise the same state: True",
            *(
                rf"^\s+[1-5]\s+{name}\s+-?\d+\.\d\d\s+\d+\s+(True|False)\s+.*True$"
                for name in ("aggressive", "conservative", "left", "right", "cautious")
            ),
            r"^best: \w+ \(return -?\d+\.\d\d\)$",
            r"reproduces the five branches bit for bit: True",
        ],
    ),
    "multi_turn": (
        ["trunk_and_branches.png", "branch_returns.png", "episode_return.png"],
        [
            r"^\d+ decision points:$",
            r"replaying the trunk's \d+ actions from the start reproduces its rewards "
            r"bit for bit: True",
            r"^multi-turn \(best of 3 every 4 steps\): episode return -?\d+\.\d\d over \d+ "
            r"steps, crashed: (True|False), episode ended: True$",
            r"^no branching \(3 rollouts of the same policy from the same start\): return "
            r"-?\d+\.\d\d ± \d+\.\d\d",
            r"^gain of select-and-continue over the no-branching mean: [+-]\d+\.\d\d$",
        ],
    ),
    "train_merge": (
        ["learning_curve.png", "crash_rate.png"],
        [
            r"^trained: \d+ env frames, \d+ iterations$",
            r"^offline wandb run: .*/run/wandb/offline-run-\S+$",
            r"wandb sync .*offline-run-\S+$",
            r"wandb sync --dry-run: Would sync 1 run",
            r"the offline run holds [1-9]\d* eval/return and 1 eval/final_return values "
            r"\(\d+ history rows in all\); they match: True$",
            r"^\| grpo_branch \(trained\) \|",
            r"^learning curve: ",
        ],
    ),
    "custom_reward_and_vehicle": (
        ["reward_components.png", "patience.png"],
        [
            r"reward components in the env output: \['collision_reward', 'right_lane_reward', "
            r"'high_speed_reward', 'on_road_reward'\]",
            r"under highway-env's reward, -?\d+\.\d\d under the safety-first reward",
            r"same rewards on the same actions, max \|difference\| = "
            r"(0\.0e\+00|\d\.\de-(0[6-9]|1\d))",
            r"-> StateMismatchError: the state was captured from another scenario or config",
            r"^branch_rollout on the transformed env .*: branch_return \[",
            r"^traffic: \d+ PatientIDM vehicles",
            r"restored patience and stuck equal the snapshot's, bit for bit: True",
            r"replaying \d+ steps after the restore gives the same states: True",
            r"UnknownFieldError: MoodyIDM\.mood is not a field the highway codec knows",
        ],
    ),
}


def assert_real_image(path: Path) -> None:
    """A PNG that loads, is not tiny, and holds more than a few colours."""
    assert path.is_file(), f"{path.name} was not written"
    image = mpimg.imread(path)
    assert image.ndim == 3 and image.shape[0] >= 100 and image.shape[1] >= 100, image.shape
    pixels = image.reshape(-1, image.shape[-1])
    assert np.ptp(pixels, axis=0).max() > 0, f"{path.name} is all one colour"
    assert len(np.unique(pixels, axis=0)) > 20, f"{path.name} is nearly blank"


def test_every_tutorial_is_run():
    assert TUTORIALS, "no tutorials found"
    assert set(EXPECTED) <= set(RUN_HERE), set(EXPECTED) - set(RUN_HERE)


def run_quick(name: str, out: Path) -> subprocess.CompletedProcess:
    """``python tutorials/<name>.py --quick --out <out>/out``, from ``out``."""
    # A user's fresh shell: not the wandb service an in-process test of this session may
    # have started (its WANDB_SERVICE variable would make the tutorial's run its client).
    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")}
    return subprocess.run(
        [sys.executable, str(ROOT / "tutorials" / f"{name}.py"), "--quick", "--out", "out"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=out,  # anything a tutorial writes next to its cwd lands in the temporary folder
        env=env,
    )


@pytest.fixture(scope="module")
def quick_runs(request, tmp_path_factory):
    """The selected tutorials' quick runs, two at a time, the longest first."""
    names = {
        item.callspec.params["name"]
        for item in request.session.items
        if getattr(item, "originalname", None) == "test_tutorial_quick"
    }
    order = sorted(names, key=lambda n: (n != "train_merge", n))
    pool = ThreadPoolExecutor(max_workers=2)
    runs = {}
    for name in order:
        folder = tmp_path_factory.mktemp(name)
        runs[name] = (folder / "out", pool.submit(run_quick, name, folder))
    yield runs
    pool.shutdown(wait=True, cancel_futures=True)


# The longest quick runs are slow-marked (the default suite's 10-minute budget).
SLOW_TUTORIALS = {
    "branch_scripted_policies",
    "multi_turn",
    "custom_reward_and_vehicle",
    "train_merge",
}


@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=pytest.mark.slow) if n in SLOW_TUTORIALS else n for n in RUN_HERE],
)
def test_tutorial_quick(name, quick_runs):
    out, future = quick_runs[name]
    result: subprocess.CompletedProcess = future.result(timeout=600)
    assert result.returncode == 0, f"{name} --quick failed:\n{result.stderr[-4000:]}"
    pictures, patterns = EXPECTED.get(name, ([], []))
    for pattern in patterns:
        assert re.search(pattern, result.stdout, flags=re.M), (
            f"{name}: no line matches {pattern!r} in:\n{result.stdout}"
        )
    for picture in pictures:
        assert_real_image(out / picture)
    written = sorted(out.rglob("*.png"))
    assert written, f"{name} wrote no picture into --out"
    for path in written:
        if path.parent == out:
            assert_real_image(path)


@pytest.mark.parametrize("name", TUTORIALS)
def test_tutorial_is_documented(name):
    source = (ROOT / "tutorials" / f"{name}.py").read_text()
    assert source.startswith("# ruff: noqa: T201\n"), name
    assert '"""' in source.split("\n", 2)[1], f"{name} has no module docstring"
    assert "--quick" in source and "--out" in source, name
    docs = (ROOT / "docs" / "tutorials.md").read_text()
    assert f"python tutorials/{name}.py" in docs, f"docs/tutorials.md has no section for {name}"


def test_docs_images_exist():
    docs = ROOT / "docs" / "tutorials.md"
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", docs.read_text())
    for image in images:
        assert not image.startswith(("/", "http")), image
        assert (docs.parent / image).is_file(), f"docs/tutorials.md embeds a missing {image}"


def test_the_merge_tutorials_runs_compose_and_the_full_one_keeps_its_budget():
    # merge-v0 trains on the tensor simulator: experiment=quick's 400,000 frames, which
    # the tutorial's docstring promises (they took an hour on highway-env's workers).
    import importlib.util

    from torchrl_grpo.training import compose_config

    spec = importlib.util.spec_from_file_location("train_merge", ROOT / "tutorials/train_merge.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    cfg = compose_config(module.FULL, conf_dir=ROOT / "conf")
    assert cfg.env.scenario == "merge-v0"
    assert str(cfg.env.backend) in ("auto", "tensor")
    assert cfg.experiment.total_frames == 400_000
    assert "400,000 frames" in module.__doc__
    # The short form runs only with -m slow: its overrides are composed here too, so that
    # a retired key in them fails the default suite (logger.video did, for five days).
    assert compose_config(module.QUICK, conf_dir=ROOT / "conf").env.scenario == "merge-v0"
