"""Train a driving policy: GRPO with snapshot branching (default), GRPO with episode groups, PPO.

    python scripts/train.py                                   # highway-fast-v0, GRPO with branching
    python scripts/train.py env=merge algo.group_size=8 logger=csv
    python scripts/train.py -m seed=0,1,2 algo=grpo_branch,grpo_episode,ppo
    python scripts/train.py resume=outputs/<day>/<run>/last.pt   # continue exactly

The config lives in conf/ (one folder per group); see docs/training.md.
"""

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

import torchrl_grpo.experimental  # noqa: F401  (registers algo=grpo_lab for docs/lab's commands)
from torchrl_grpo.training import Trainer, register_configs
from torchrl_grpo.training.compose import resume_config
from torchrl_grpo.training.teacher_runs import train_with_teachers

register_configs()
CONF = str(Path(__file__).resolve().parents[1] / "conf")


@hydra.main(config_path=CONF, config_name="config", version_base=None)
def main(cfg: DictConfig) -> float:
    """Train, evaluate, and print where the outputs are."""
    logging.getLogger("torchrl_grpo").setLevel(logging.INFO)
    hydra_cfg = HydraConfig.get()
    if cfg.get("resume"):
        # The checkpoint's config, the command line's overrides on top; the run goes on
        # writing into its own folder.
        cfg = resume_config(cfg, list(hydra_cfg.overrides.task), conf_dir=CONF)
    run_dir = cfg.experiment.out_dir or (
        Path(cfg.resume).parent if cfg.get("resume") else hydra_cfg.runtime.output_dir
    )
    if cfg.algo.get("teacher_runs"):
        # The teachers first (experiment=best), then the student: one command.
        result = train_with_teachers(cfg, run_dir, conf_dir=CONF)
    else:
        result = Trainer(cfg, run_dir=run_dir).train()
    status = "interrupted (Ctrl-C)" if result.interrupted else "done"
    print(f"\n{status}: {result.frames} env frames, {result.iterations} iterations")
    if result.final:
        f = result.final
        print(
            f"final evaluation: return {f['return']:.2f} ± {f['return_std']:.2f}, "
            f"crash rate {100 * f['crash_rate']:.1f}%, speed {f['speed']:.1f} m/s "
            f"({int(f['episodes'])} episodes)"
        )
    print(f"run folder:  {result.run_dir}")
    print(f"checkpoint:  {result.checkpoint}")
    if result.logs is not None:
        print(f"logs:        {result.logs}")
        if str(cfg.logger.backend) == "wandb":  # offline
            print(f"             upload with: wandb sync {result.logs}")
    for label, path in (
        ("results:", result.results_table),
        ("curve:", result.curve),
        ("video:", result.video),
    ):
        if path is not None:
            print(f"{label:<12} {path}")
    plots = Path(result.run_dir) / "plots"
    if plots.is_dir():
        print(f"{'plots:':<12} {plots}")
    # Hydra sweepers read the returned value (e.g. for Optuna); NaN when not evaluated.
    return float(result.final.get("return", float("nan")))


if __name__ == "__main__":
    main()
