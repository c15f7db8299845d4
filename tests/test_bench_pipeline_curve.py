"""benchmarks/bench_pipeline_curve.py: a nested pipeline's stages joined end to end."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_pipeline_curve  # noqa: E402

from torchrl_grpo.training.checkpoint import save_checkpoint  # noqa: E402


def _stage(
    folder: Path, rows: list[tuple], search_frames: int = 0, processes: int | None = None
) -> Path:
    """A finished run folder: its checkpoint's evaluations.

    Each row is (frames, wall seconds, return), or with a fourth figure, the search
    frames the evaluation recorded.
    """
    history = []
    for frames, seconds, ret, *recorded in rows:
        row = {"frames": frames, "wall_seconds": seconds, "return": ret, "crash_rate": 0.0}
        history.append(row | ({"search_frames": recorded[0]} if recorded else {}))
    checkpoint = {"eval_history": history, "search_frames": search_frames}
    if processes is not None:  # the pipeline's config: its teachers trained side by side
        checkpoint["config"] = {"algo": {"teacher_processes": processes}}
    save_checkpoint(checkpoint, folder / "last.pt")
    return folder


def test_a_nested_pipeline_joins_its_stages_frames_search_steps_and_minutes(tmp_path):
    # The run (100 frames, 60 s), round 1 (40 own + 400 search frames, 120 s), round 2.
    run = tmp_path / "r2"
    _stage(run / "teachers" / "0" / "teachers" / "0", [(0, 0, 1.0), (50, 30, 2.0), (100, 60, 3.0)])
    _stage(run / "teachers" / "0", [(0, 0, 0.5), (20, 60, 4.0), (40, 120, 5.0)], 400)
    _stage(run, [(0, 0, 4.5), (10, 30, 6.0)], 200)
    rows, stages = bench_pipeline_curve.pipeline_curve(run)
    # Every stage's frame-0 row (an untrained network) is left out.
    assert [r["return"] for r in rows] == [2.0, 3.0, 4.0, 5.0, 6.0]
    # Round 1 at 20 own frames: the run's 100, its 20 and half its 400 search frames.
    assert [r["frames"] for r in rows] == [50, 100, 100 + 20 + 200, 100 + 440, 540 + 10 + 200]
    assert [r["minutes"] for r in rows] == [0.5, 1.0, 2.0, 3.0, 3.5]
    assert [name for name, _, _ in stages] == ["r2/teachers/0/teachers/0", "r2/teachers/0", "r2"]
    assert [frames for _, frames, _ in stages] == [100, 540, 750]


def test_the_search_steps_each_evaluation_recorded_are_counted_as_they_are(tmp_path):
    # The run (100 frames), then a student whose search took 300 of its 400 steps by its
    # first evaluation: the rows' counts, not a share in proportion to its own frames.
    run = tmp_path / "r1"
    _stage(run / "teachers" / "0", [(0, 0, 1.0), (100, 60, 2.0)])
    _stage(run, [(0, 0, 1.5, 0), (20, 60, 3.0, 300), (40, 120, 4.0, 400)], 400)
    rows, stages = bench_pipeline_curve.pipeline_curve(run)
    assert [r["frames"] for r in rows] == [100, 100 + 20 + 300, 100 + 40 + 400]
    assert [frames for _, frames, _ in stages] == [100, 540]


def test_teachers_trained_side_by_side_start_at_the_same_minute(tmp_path):
    # Two teachers in two processes: A (100 frames in 60 s), B (200 frames in 120 s,
    # evaluated at 60 s and 120 s), then the student (10 frames in 30 s).
    run = tmp_path / "pair"
    _stage(run / "teachers" / "0", [(0, 0, 1.0), (100, 60, 2.0)])
    _stage(run / "teachers" / "1", [(0, 0, 1.0), (100, 60, 3.0), (200, 120, 4.0)])
    _stage(run, [(0, 0, 4.0), (10, 30, 5.0)], processes=2)
    rows, stages = bench_pipeline_curve.pipeline_curve(run)
    # At minute 1 both have trained 100 frames; at minute 2, A is done and B at 200.
    assert [(r["minutes"], r["frames"], r["return"]) for r in rows] == [
        (1.0, 200, 2.0),
        (1.0, 200, 3.0),
        (2.0, 300, 4.0),
        (2.5, 310, 5.0),
    ]
    assert stages == [
        ("pair/teachers/0", 200, 1.0),
        ("pair/teachers/1", 300, 2.0),
        ("pair", 310, 2.5),
    ]
    # The control: the same folders trained one after another (one process).
    _stage(run, [(0, 0, 4.0), (10, 30, 5.0)], processes=1)
    _, serial = bench_pipeline_curve.pipeline_curve(run)
    assert serial == [
        ("pair/teachers/0", 100, 1.0),
        ("pair/teachers/1", 300, 3.0),
        ("pair", 310, 3.5),
    ]


def test_a_plain_run_is_a_pipeline_of_one_stage(tmp_path):
    _stage(tmp_path / "ppo", [(0, 0, 1.0), (50, 30, 2.0), (100, 60, 3.0)])
    rows, stages = bench_pipeline_curve.pipeline_curve(tmp_path / "ppo")
    assert [(r["frames"], r["minutes"]) for r in rows] == [(50, 0.5), (100, 1.0)]
    assert stages == [("ppo", 100, 1.0)]


def test_a_folder_without_a_checkpoint_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=f"no checkpoint at {tmp_path}"):
        bench_pipeline_curve.pipeline_curve(tmp_path)
