"""Outputs where the user said, and what the scripts list: run folders, train.log, --help."""

from __future__ import annotations

import os

import pytest
from train_setup import ROOT, TINY, compose_config, run_script

from torchrl_grpo.training import load_checkpoint


def _script(script: str, args: list[str], cwd, timeout: float = 180):
    return run_script(script, args, timeout=timeout, cwd=cwd)


@pytest.mark.slow  # the default suite's 10-minute budget
def test_out_dir_holds_hydras_files_and_a_resume_writes_into_its_own_folder(tmp_path):
    tiny = [*TINY, "experiment.checkpoint_every=1"]
    first = _script(
        "train.py", [*tiny, "experiment.total_frames=20", "experiment.out_dir=runs/x"], tmp_path
    )
    assert first.returncode == 0, first.stderr[-3000:]
    run = tmp_path / "runs" / "x"
    # Everything in runs/x: no outputs/<date>/ folder beside it.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]
    assert (run / ".hydra" / "config.yaml").is_file()
    assert "train.log" in os.listdir(run)
    frames = load_checkpoint(run / "last.pt")["frames"]
    # A resume without out_dir goes on in the checkpoint's folder, its log appended.
    resumed = _script(
        "train.py", [f"resume={run / 'last.pt'}", "experiment.total_frames=150"], tmp_path
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]
    assert "run folder:  runs/x" in resumed.stdout
    assert load_checkpoint(run / "last.pt")["frames"] > frames
    assert "resumed from" in (run / "train.log").read_text()


def test_evaluate_with_a_wrong_path_leaves_no_folder(tmp_path):
    (tmp_path / "runs" / "x").mkdir(parents=True)
    proc = _script("evaluate.py", ["checkpoint=runs/x/typo.pt", "hydra.run.dir=hydra"], tmp_path)
    assert proc.returncode != 0
    assert "typo.pt" in proc.stderr
    assert os.listdir(tmp_path / "runs" / "x") == []


@pytest.mark.slow  # 9 s: every choice of --help composed
def test_help_lists_only_choices_that_compose():
    proc = _script("train.py", ["--help"], ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    groups = proc.stdout.split("== Configuration groups ==")[1].split("== Config ==")[0]
    lines = [line for line in groups.splitlines() if ": " in line and "(" not in line]
    listed = {g: c.split(", ") for g, c in (line.split(": ") for line in lines)}
    assert set(listed) >= {"algo", "env", "model", "experiment", "logger", "optim"}
    assert "base_grpo" not in proc.stdout and "base_env" not in proc.stdout
    for group, choices in listed.items():
        if group == "rollout":  # chosen by algo (rollout: ${algo})
            continue
        for choice in choices:
            compose_config([f"{group}={choice}"])


def test_evaluate_help_lists_only_the_env_choices_that_compose():
    # The template evaluate.py --help prints (in this process: a subprocess costs ~6 s).
    from hydra import compose, initialize_config_dir

    from torchrl_grpo.training import register_configs

    register_configs()
    with initialize_config_dir(str(ROOT / "conf"), version_base=None):
        text = compose("evaluate", return_hydra_config=True).hydra.help.template
    groups = text.split("== Configuration groups ==")[1].split("== Config ==")[0]
    lines = [line for line in groups.splitlines() if ": " in line and "(" not in line]
    assert [line.split(": ")[0] for line in lines] == ["env"]  # evaluate composes env only
    assert "base_" not in text
    for choice in lines[0].split(": ")[1].split(", "):
        compose_config([f"env={choice}"], config_name="evaluate")
