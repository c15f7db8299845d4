"""OmegaConf resolvers of ``conf/``: where a run writes, and the choices ``--help`` lists.

``conf/config.yaml`` sets Hydra's run folder with ``${run_dir:...}``: the folder the
user named (``experiment.out_dir``), else the folder of the checkpoint a run resumes
(it goes on writing there), else Hydra's dated folder. Hydra's ``.hydra/`` and
``train.log`` then land in the run folder itself. ``--help`` lists the choices of each
config group with ``${config_choices:}``: the YAML files of ``conf/<group>/``, not the
schemas Hydra's own list shows beside them (``algo=base_grpo`` is no choice).
"""

from __future__ import annotations

import re
from pathlib import Path

from omegaconf import OmegaConf

__all__ = [
    "CONF_DIR",
    "SCENARIO_NETWORKS",
    "config_choices",
    "env_name",
    "register_resolvers",
    "run_dir",
    "scenario_network",
]

#: The network of ``model=auto`` (the default) per scenario where it is not ``scene``:
#: merge-v0's recipe reads the Kinematics table itself, whose ego x tells how far the
#: merge is, and roundabout-v0's, whose cars drive on curves that the scene's per-lane
#: features (built for straight lanes) do not describe (docs/results.md, section 5), and
#: intersection-v0's, where the ego drives along y and the crossing cars along x, while
#: the scene features read lanes from y and gaps along x (section 6).
#: Both kinds share one schema.
SCENARIO_NETWORKS = {"merge-v0": "mlp", "roundabout-v0": "mlp", "intersection-v0": "mlp"}

#: The config folder of a source checkout (``conf/`` beside the package).
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def run_dir(out_dir: str | None, resume: str | None, default: str) -> str:
    """The run folder: ``out_dir``, else the resumed checkpoint's folder, else ``default``.

    Example:
        >>> run_dir("runs/x", None, "outputs/today")
        'runs/x'
        >>> run_dir(None, "runs/y/last.pt", "outputs/today")
        'runs/y'
        >>> run_dir(None, None, "outputs/today")
        'outputs/today'
    """
    if out_dir:
        return str(out_dir)
    if resume:
        return str(Path(resume).parent)
    return str(default)


def config_choices(*groups: str, conf_dir: str | Path | None = None) -> str:
    """One line per config group of ``conf_dir``: ``group: choice, choice, ...``.

    A choice is a YAML file of the group's folder; the schemas the files start from
    (``base_*``, registered by :func:`~torchrl_grpo.training.register_configs`) are not.

    Args:
        groups: the groups to list (none: every group), as ``${config_choices:env}``
            in a help template (evaluate.py composes ``env`` only).
        conf_dir: the config folder (default :data:`CONF_DIR`).

    Example:
        >>> print(config_choices().splitlines()[0])
        algo: distill, grpo_branch, grpo_episode, grpo_lab, ppo, search_distill
        >>> print(config_choices("env"))
        env: highway, highway_fast, intersection, merge, roundabout
    """
    lines = []
    folders = sorted(p for p in Path(conf_dir or CONF_DIR).iterdir() if p.is_dir())
    for group in folders:
        if groups and group.name not in groups:
            continue
        choices = sorted(f.stem for f in group.glob("*.yaml"))
        if choices:
            lines.append(f"{group.name}: {', '.join(choices)}")
    return "\n".join(lines)


def env_name(scenario: str) -> str:
    """A scenario's short name, for run folders and run names.

    Example:
        >>> env_name("highway-fast-v0")
        'highway_fast'
    """
    return re.sub(r"-v\d+$", "", str(scenario)).replace("-", "_")


def scenario_network(scenario: str) -> str:
    """The network kind ``model=auto`` gives a scenario: :data:`SCENARIO_NETWORKS`, else ``scene``.

    Example:
        >>> scenario_network("merge-v0"), scenario_network("highway-fast-v0")
        ('mlp', 'scene')
    """
    return SCENARIO_NETWORKS.get(str(scenario), "scene")


def register_resolvers() -> None:
    """Register the resolvers of ``conf/`` with OmegaConf (idempotent).

    ``run_dir``, ``env_name``, ``config_choices`` and ``scenario_network``.

    Example:
        >>> register_resolvers()
        >>> cfg = OmegaConf.create({"out": None, "resume": "runs/y/last.pt",
        ...                         "dir": "${run_dir:${out},${resume},outputs/today}"})
        >>> cfg.dir
        'runs/y'
    """
    resolvers = (
        ("run_dir", run_dir),
        ("env_name", env_name),
        ("config_choices", config_choices),
        ("scenario_network", scenario_network),
    )
    for name, resolver in resolvers:
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, resolver)
