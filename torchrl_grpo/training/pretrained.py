"""The saved policies of finished runs: to start a new run from, or to act as teachers.

A run's checkpoint holds the policy it evaluates (the weight average where the run kept
one) and the config it was built from. ``init_from=PATH`` starts a run from those
weights (fine-tuning: another algorithm, recipe or budget on top of a trained policy);
``algo=distill`` loads whole runs as teachers (:mod:`.teachers`). Either way the run's
observations must mean what the saved run's meant: the same scenario and env config.
"""

from __future__ import annotations

import logging

from omegaconf import DictConfig, OmegaConf
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor

from torchrl_grpo.training.checkpoint import load_checkpoint, model_changes
from torchrl_grpo.training.env_builder import env_overrides
from torchrl_grpo.training.model_builder import make_policy

__all__ = ["FREE_MODEL_KEYS", "check_same_env", "init_policy", "load_run_policy"]

log = logging.getLogger(__name__)

#: ``model`` keys that may differ from the saved run's under ``init_from``: they weigh
#: or train the same parameters (a crash head's weight on the logits, a prior's bonus,
#: which data an ensemble's members fit).
FREE_MODEL_KEYS = frozenset({"crash_aversion", "crash_margin", "prior_weight", "bagging"})


def check_same_env(role: str, saved_env: DictConfig, env_cfg: DictConfig) -> None:
    """Refuses a saved run of another scenario or env config: its inputs meant other things.

    Args:
        role: how the error names the saved run (``"teacher runs/a/last.pt"``).
        saved_env: the saved run's ``env`` config.
        env_cfg: this run's ``env`` config.

    Raises:
        ValueError: naming the saved run and both configs.

    Example:
        >>> from omegaconf import OmegaConf
        >>> a = OmegaConf.create({"scenario": "highway-fast-v0", "config": {}})
        >>> b = OmegaConf.create({"scenario": "merge-v0", "config": {}})
        >>> check_same_env("init_from=a.pt", a, a)
        >>> try:
        ...     check_same_env("init_from=a.pt", a, b)
        ... except ValueError as err:
        ...     print(str(err)[:60])
        init_from=a.pt was trained on highway-fast-v0 with env.confi
    """
    got = (str(saved_env.scenario), env_overrides(saved_env))
    want = (str(env_cfg.scenario), env_overrides(env_cfg))
    if got != want:
        raise ValueError(
            f"{role} was trained on {got[0]} with env.config {got[1]}; this run is on "
            f"{want[0]} with {want[1]}: its observations would mean other things"
        )


def load_run_policy(
    path: str, env_cfg: DictConfig, env: EnvBase, role: str | None = None
) -> ProbabilisticActor:
    """The saved policy of the run at ``path``, built from that run's own ``model`` config.

    Args:
        path: a checkpoint written by a training run (``last.pt``).
        env_cfg: this run's ``env`` config (checked against the saved run's).
        env: an env of that config, for the specs.
        role: how an error names the saved run (default: its path).

    Raises:
        FileNotFoundError: no file at ``path`` (naming it).
        ValueError: a file that is not a checkpoint, or a run of another env.

    Example:
        >>> import tempfile, torch
        >>> from torchrl_grpo.training import compose_config, make_env
        >>> from torchrl_grpo.training.checkpoint import save_checkpoint
        >>> from torchrl_grpo.training.config import to_container
        >>> cfg = compose_config(["experiment=smoke", "model=mlp"])
        >>> env = make_env(cfg.env, seed=0)
        >>> policy = make_policy(cfg.model, env)
        >>> path = save_checkpoint({"config": to_container(cfg), "policy": policy.state_dict()},
        ...                        tempfile.mkdtemp() + "/last.pt")
        >>> loaded = load_run_policy(str(path), compose_config(["experiment=smoke"]).env, env)
        >>> state = env.reset()
        >>> torch.equal(loaded(state.clone())["logits"], policy(state.clone())["logits"])
        True
    """
    ckpt = load_checkpoint(path)
    # Untyped: the algo's schema is not needed, and typing it would import the algos.
    run_cfg = OmegaConf.create(ckpt["config"])
    check_same_env(role or path, run_cfg.env, env_cfg)
    policy = make_policy(run_cfg.model, env)
    policy.load_state_dict(ckpt["policy"])
    return policy


def init_policy(path: str, policy: ProbabilisticActor, cfg: DictConfig) -> None:
    """Loads the saved policy of the run at ``path`` into this run's ``policy``.

    The weights must fit this run's network: the same ``model`` config, up to the keys
    that only weigh or train the same parameters (:data:`FREE_MODEL_KEYS`). As for a
    resume, another ``model.prior`` is refused (:func:`~.checkpoint.model_changes`).
    Only the policy is loaded: a value network, an optimiser, a reference policy and a
    weight average start from scratch (the reference and the average from these
    weights, as they do from fresh ones).

    Args:
        path: a checkpoint written by a training run (``last.pt``).
        policy: this run's policy, built from ``cfg.model``.
        cfg: this run's config.

    Raises:
        FileNotFoundError: no file at ``path`` (naming it).
        ValueError: a file that is not a checkpoint, a run of another env, or weights
            that do not fit this run's network (naming the ``model`` keys that differ).

    Example:
        >>> import tempfile, torch
        >>> from torchrl_grpo.training import compose_config, make_env
        >>> from torchrl_grpo.training.checkpoint import save_checkpoint
        >>> from torchrl_grpo.training.config import to_container
        >>> cfg = compose_config(["experiment=smoke"])
        >>> env = make_env(cfg.env, seed=0)
        >>> trained, fresh = make_policy(cfg.model, env), make_policy(cfg.model, env)
        >>> path = save_checkpoint({"config": to_container(cfg), "policy": trained.state_dict()},
        ...                        tempfile.mkdtemp() + "/last.pt")
        >>> init_policy(str(path), fresh, cfg)
        >>> state = env.reset()
        >>> torch.equal(fresh(state.clone())["logits"], trained(state.clone())["logits"])
        True
    """
    ckpt = load_checkpoint(path)
    saved = OmegaConf.create(ckpt["config"])
    check_same_env(f"init_from={path}", saved.env, cfg.env)
    current = OmegaConf.to_container(cfg.model, resolve=True, enum_to_str=True)
    changed = model_changes(ckpt["config"]["model"], current, free=FREE_MODEL_KEYS)
    if changed:
        raise ValueError(
            f"init_from={path}: its policy does not fit this run's network ({changed})"
        )
    try:
        policy.load_state_dict(ckpt["policy"])
    except RuntimeError as err:  # a model the config does not describe (a custom build)
        raise ValueError(
            f"init_from={path}: its policy does not fit this run's network: "
            + str(err).splitlines()[0]
        ) from err
    log.info("init_from=%s: the policy starts from that run's saved weights", path)
