# ruff: noqa: T201
"""Train GRPO with branching on merge-v0, log to wandb offline, plot the learning curve.

It teaches the training entry point from Python, the same one ``scripts/train.py`` runs:

* composing the Hydra config of ``conf/`` with overrides (``env=merge``,
  ``experiment=quick``, ``logger=wandb``, ...) and running
  :class:`torchrl_grpo.training.Trainer`;
* where a run leaves its outputs (:class:`~torchrl_grpo.training.TrainResult`): the
  checkpoint, ``eval_history.jsonl``, ``results.md``, and the offline wandb run;
* the offline wandb run: no network is used; ``wandb sync <folder>`` uploads it later
  (the tutorial checks it with ``wandb sync --dry-run``, which uploads nothing) and its
  metrics can be read back from the run file itself, without uploading;
* plotting the learning curve (evaluation return and crash rate against env frames)
  from the run's evaluation history, with the scripted baselines of the final
  evaluation as reference lines.

Run it::

    python tutorials/train_merge.py           # 400,000 frames: about 4 min on 2 cores
    python tutorials/train_merge.py --quick   # a few hundred frames (the tests' form)
    python tutorials/train_merge.py algo.group_size=4 seed=1   # any Hydra override

Pictures (in ``--out``, default ``outputs/tutorials/train_merge``):
``learning_curve.png`` and ``crash_rate.png`` (drawn by the library's
``plot_learning_curve``); the run folder is ``<out>/run``.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from torchrl_grpo.training import (
    Trainer,
    TrainResult,
    plot_learning_curve,
    register_configs,
)

NAME = "train_merge"
CONF = Path(__file__).resolve().parents[1] / "conf"

#: The tutorial's run: merge-v0 with its own defaults on the tensor simulator, GRPO with
#: branching (the default algo) for experiment=quick's 400,000 frames, wandb offline, an
#: evaluation after every iteration so that the curve has points.
FULL = [
    "env=merge",
    "experiment=quick",
    "logger=wandb",
    "experiment.eval_every=1",
]
#: ``--quick``: experiment=smoke-sized (one in-process simulator, a tiny network).
QUICK = [
    "env=merge",
    "experiment=smoke",
    "logger=wandb",
    "experiment.eval_every=1",
    "experiment.final_eval_episodes=1",
    "experiment.baselines=[slower]",
]


# ---------------------------------------------------------------------------- wandb
_BLOCK = 32 * 1024  # LevelDB log blocks
_FULL, _FIRST, _MIDDLE, _LAST = 1, 2, 3, 4


def read_offline_history(run_folder: Path) -> list[dict]:
    """The history rows (``wandb.log`` payloads) of an offline run, read from its file.

    ``<run_folder>/run-<id>.wandb`` is wandb's transaction log, the file ``wandb sync``
    uploads: a 7-byte header, then 32 KiB blocks of chunks (7-byte header: CRC32,
    length, type full / first / middle / last) that join into protobuf ``Record``
    messages. wandb has no public reader for offline runs; this one reads the history
    records only.

    Args:
        run_folder: the ``offline-run-*`` folder.

    Returns:
        One ``{metric: value}`` dict per logged row.
    """
    from wandb.proto import wandb_internal_pb2 as pb  # wandb's own message definitions

    (path,) = run_folder.glob("run-*.wandb")
    raw = path.read_bytes()
    if raw[:4] != b":W&B":
        raise ValueError(f"{path} is not a wandb run file")
    rows, pending, pos = [], b"", 7
    while pos + 7 <= len(raw):
        room = _BLOCK - pos % _BLOCK
        _crc, length, kind = struct.unpack("<IHB", raw[pos : pos + 7])
        if room < 7 or (kind == 0 and length == 0):  # block padding
            pos += room
            continue
        chunk = raw[pos + 7 : pos + 7 + length]
        pos += 7 + length
        if kind in (_FIRST, _MIDDLE):
            pending += chunk
            continue
        data, pending = (pending + chunk if kind == _LAST else chunk), b""
        record = pb.Record()
        record.ParseFromString(data)
        if record.WhichOneof("record_type") == "history":
            rows.append(
                {
                    item.key or "/".join(item.nested_key): json.loads(item.value_json)
                    for item in record.history.item
                }
            )
    return rows


def check_with_wandb_cli(run_folder: Path) -> str:
    """``wandb sync --dry-run <folder>``: what an upload would do, uploading nothing."""
    env = {**os.environ, "WANDB_MODE": "offline"}
    cmd = [sys.executable, "-m", "wandb", "sync", "--dry-run", str(run_folder)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stdout}\n{out.stderr}")
    return " ".join(line.removeprefix("wandb:").strip() for line in out.stderr.splitlines())


# ---------------------------------------------------------------------------- plot
# ---------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("overrides", nargs="*", help="more Hydra overrides, e.g. seed=1")
    p.add_argument("--quick", action="store_true", help="short form (tests): tiny budget")
    p.add_argument("--out", type=Path, default=Path("outputs/tutorials") / NAME)
    return p.parse_args(argv)


def train(overrides: list[str], run_dir: Path) -> TrainResult:
    """Compose ``conf/config.yaml`` with ``overrides`` and train into ``run_dir``."""
    register_configs()  # the dataclass schemas that check every key and value
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose("config", overrides=overrides)
    return Trainer(cfg, run_dir=run_dir).train()


def main(argv: list[str] | None = None) -> None:
    """Train, find the offline wandb run, plot the learning curve."""
    args = parse_args(argv)
    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    overrides = (QUICK if args.quick else FULL) + list(args.overrides)
    run_dir = args.out / "run"
    print("training; the same run from the command line:")
    print(f"  python scripts/train.py {' '.join(overrides)} experiment.out_dir={run_dir}\n")
    result = train(overrides, run_dir)
    print(f"\ntrained: {result.frames} env frames, {result.iterations} iterations")
    print(f"run folder: {result.run_dir}")
    print(f"checkpoint: {result.checkpoint}")

    # The offline wandb run.
    offline = result.logs
    if offline is None or not offline.name.startswith("offline-run-"):
        raise RuntimeError(f"expected an offline wandb run folder, got {offline}")
    print(f"offline wandb run: {offline}")
    print(f"  upload it (needs network and `wandb login`): wandb sync {offline}")
    print(f"  wandb sync --dry-run: {check_with_wandb_cli(offline)}")

    # The evaluation history: eval_history.jsonl, and the same numbers in the wandb run.
    history = [json.loads(line) for line in (run_dir / "eval_history.jsonl").open()]
    logged = read_offline_history(offline)
    eval_logged = [row["eval/return"] for row in logged if "eval/return" in row]
    final_logged = [row["eval/final_return"] for row in logged if "eval/final_return" in row]
    n_final = len(final_logged)
    same = eval_logged + final_logged == [row["return"] for row in history]
    print(
        f"evaluation history: {len(history)} rows in eval_history.jsonl; the offline run "
        f"holds {len(eval_logged)} eval/return and {n_final} eval/final_return values "
        f"({len(logged)} history rows in all); they match: {same}"
    )
    print(f"{'frames':>8} {'return':>8} {'± std':>7} {'crash rate':>11}")
    for row in history:
        print(
            f"{row['frames']:>8} {row['return']:>8.2f} {row['return_std']:>7.2f} "
            f"{100 * row['crash_rate']:>10.0f}%"
        )

    # The final evaluation beside the scripted baselines (results.json), and the curve.
    results = json.loads(result.results_json.read_text())["results"]
    baselines = {r["name"]: r["summary"] for r in results if "(trained)" not in r["name"]}
    # The library's plot (the trainer draws the same into the run folder): return with
    # the baselines as dashed lines, then the crash rate.
    scenario = "merge-v0" if "env=merge" in overrides else "the scenario"
    runs = {"GRPO with branching (greedy)": [history]}
    curve = plot_learning_curve(
        runs,
        args.out / "learning_curve.png",
        title=f"{scenario}: evaluation return",
        hlines={name: summary["return"] for name, summary in baselines.items()},
    )
    plot_learning_curve(
        runs, args.out / "crash_rate.png", metric="crash_rate", title=f"{scenario}: crash rate"
    )
    print(f"\nfinal evaluation ({result.results_table}):")
    print(result.results_table.read_text().strip())
    print(f"\nlearning curve: {curve}")
    print(f"done in {time.perf_counter() - t_start:.1f} s")


if __name__ == "__main__":
    main()
