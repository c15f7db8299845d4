"""Trained policies as teachers: their checkpoints loaded, frozen, and acting as one.

``algo=distill`` trains a student on the states it visits, labelled with the mean
logits of one or more trained runs (their saved policies: the weight average where the
run kept one). The mean logits of several runs crash less than any of them
(docs/results.md, "Where the crash rate moves"); distilled, they are one network to run.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from omegaconf import DictConfig
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs import EnvBase

from torchrl_grpo.modules.ensemble import PolicyEnsemble
from torchrl_grpo.training.pretrained import load_run_policy

__all__ = ["Teachers", "has_crash_head", "load_teachers"]


class Teachers(TensorDictModuleBase):
    """Frozen logits networks that write their mean logits, without gradients.

    The mean is :class:`~torchrl_grpo.modules.PolicyEnsemble`'s, the mean logits a
    ``model.ensemble`` and ``bench_crash_rates.py --ensemble`` act with.

    With ``crash_key``, the teachers' crash heads also label each action's crash
    probability: their mean crash logits
    (:meth:`~torchrl_grpo.modules.PolicyEnsemble.crash_logits`), for a student with a
    crash head (:class:`~torchrl_grpo.objectives.TeacherCrashLoss`).

    Args:
        nets: networks that each map the observation to logits (a trained actor's
            ``policy.module[0].module``).
        in_key: the observation key.
        out_key: where the mean logits are written.
        crash_key: where the mean crash logits are written (``None``: not written).
        names: what the errors call each net (its checkpoint); by default its index.

    Raises:
        ValueError: no nets, or ``crash_key`` with a net that has no crash head (naming
            it).

    Example:
        >>> from tensordict import TensorDict
        >>> nets = [nn.Linear(3, 2) for _ in range(2)]
        >>> td = Teachers(nets)(TensorDict(observation=torch.ones(4, 3), batch_size=[4]))
        >>> mean = (nets[0](torch.ones(4, 3)) + nets[1](torch.ones(4, 3))) / 2
        >>> torch.allclose(td["teacher_logits"], mean), td["teacher_logits"].requires_grad
        (True, False)
    """

    def __init__(
        self,
        nets: Sequence[nn.Module],
        in_key: NestedKey = "observation",
        out_key: NestedKey = "teacher_logits",
        crash_key: NestedKey | None = None,
        names: Sequence[str] | None = None,
    ) -> None:
        super().__init__()
        if not nets:
            raise ValueError("Teachers needs at least one teacher")
        if crash_key is not None:
            names = list(names) if names is not None else [str(i) for i in range(len(nets))]
            headless = [n for n, net in zip(names, nets, strict=True) if not has_crash_head(net)]
            if headless:
                which = "teacher {} has" if len(headless) == 1 else "teachers {} have"
                raise ValueError(
                    f"a student with a crash head learns its teachers' crash heads, and "
                    f"{which.format(', '.join(headless))} none (trained with "
                    "model.crash_head=false): distil into a student without one"
                )
        net = nets[0] if len(nets) == 1 else PolicyEnsemble(list(nets))
        self.net = net.requires_grad_(False).eval()
        self.in_keys = [in_key]
        self.out_keys = [out_key] if crash_key is None else [out_key, crash_key]

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes the networks' mean logits (and crash logits) of ``tensordict``'s states."""
        observation = tensordict.get(self.in_keys[0])
        tensordict.set(self.out_keys[0], self.net(observation))
        if len(self.out_keys) > 1:
            tensordict.set(self.out_keys[1], self.net.crash_logits(observation))
        return tensordict


def has_crash_head(net: nn.Module) -> bool:
    """Whether ``net`` gives crash logits: a crash head, or an ensemble of them only.

    Example:
        >>> from torchrl_grpo.modules import CrashHead
        >>> head = CrashHead(nn.Linear(3, 4), 2)
        >>> has_crash_head(head), has_crash_head(PolicyEnsemble([head, nn.Linear(3, 2)]))
        (True, False)
    """
    if isinstance(net, PolicyEnsemble):
        return all(has_crash_head(member) for member in net.members)
    return callable(getattr(net, "crash_logits", None))


def load_teachers(
    paths: Sequence[str], env_cfg: DictConfig, env: EnvBase, crash_key: NestedKey | None = None
) -> Teachers:
    """The saved policies of the checkpoints at ``paths``, as one :class:`Teachers`.

    Each teacher keeps its own ``model`` config (networks, crash head, ensemble), so
    teachers of different architectures mix. Each must have been trained on this
    scenario and env config: its observations must mean what the student's mean.

    Args:
        paths: checkpoints written by training runs (``last.pt``).
        env_cfg: the student's ``env`` config.
        env: an env of that config, for the specs.
        crash_key: also label the teachers' mean crash logits there (see
            :class:`Teachers`).

    Raises:
        FileNotFoundError: a path holds no file (naming it).
        ValueError: no path, a file that is not a checkpoint, a teacher trained on
            another scenario or env config (naming its path and both configs), or,
            with ``crash_key``, a teacher without a crash head (naming its path).

    Example:
        >>> import tempfile
        >>> from torchrl_grpo.training import compose_config, make_env
        >>> from torchrl_grpo.training.checkpoint import save_checkpoint
        >>> from torchrl_grpo.training import make_policy
        >>> from torchrl_grpo.training.config import to_container
        >>> cfg = compose_config(["experiment=smoke"])
        >>> env = make_env(cfg.env, seed=0)
        >>> policy = make_policy(cfg.model, env)
        >>> path = save_checkpoint({"config": to_container(cfg), "policy": policy.state_dict()},
        ...                        tempfile.mkdtemp() + "/last.pt")
        >>> state = env.reset()
        >>> labelled = load_teachers([str(path)], cfg.env, env)(state.clone())
        >>> torch.equal(labelled["teacher_logits"], policy(state.clone())["logits"])
        True
    """
    if not paths:
        raise ValueError("algo.teachers is empty: give the checkpoints to distil")
    members = [
        load_run_policy(path, env_cfg, env, role=f"teacher {path}").module[0].module
        for path in paths
    ]
    return Teachers(members, crash_key=crash_key, names=list(paths))
