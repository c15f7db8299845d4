"""Evaluate a trained policy beside the scripted baselines: a table, a video, the plots.

    python scripts/evaluate.py checkpoint=outputs/<day>/<run>/last.pt
    python scripts/evaluate.py checkpoint=.../last.pt episodes=50 baselines=[slower,rule]
    python scripts/evaluate.py checkpoint=.../last.pt baselines=[slower,runs/ppo/last.pt]  # paired
    python scripts/evaluate.py env=merge                     # baselines only

Deterministic policy (greedy), episode i from seed ``seed + i``; see docs/training.md.
"""

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

import torchrl_grpo.experimental  # noqa: F401  (reads algo=grpo_lab checkpoints)
from torchrl_grpo.training import register_configs
from torchrl_grpo.training.evaluation import evaluate_checkpoint

register_configs()
CONF = str(Path(__file__).resolve().parents[1] / "conf")


@hydra.main(config_path=CONF, config_name="evaluate", version_base=None)
def main(cfg: DictConfig) -> None:
    """Evaluate and print the table and where the files are."""
    logging.getLogger("torchrl_grpo").setLevel(logging.INFO)
    keys = {o: o.lstrip("+~").split("=")[0] for o in HydraConfig.get().overrides.task}
    chosen_env = [o for o, key in keys.items() if key == "env" or key.startswith("env.")]
    if cfg.checkpoint and chosen_env:
        # A checkpoint is evaluated on the env it was trained on: say so, never ignore it.
        raise SystemExit(
            f"{chosen_env[0]}: a checkpoint is evaluated on its own env (its config); "
            "leave env out, or give no checkpoint to evaluate the baselines on another env"
        )
    if cfg.out_dir:
        out_dir = Path(cfg.out_dir)
    elif cfg.checkpoint:
        out_dir = Path(cfg.checkpoint).resolve().parent / "eval"
    else:
        out_dir = Path(HydraConfig.get().runtime.output_dir)
    report = evaluate_checkpoint(cfg, out_dir)
    print(report.files["table"].read_text())
    for kind, path in report.files.items():
        print(f"{kind + ':':<7} {path}")


if __name__ == "__main__":
    main()
