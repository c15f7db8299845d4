"""Policy distillation: the KL divergence from a teacher's action distribution to the policy's.

A teacher here is a trained policy, or the mean logits of several, that labels every
state the student visits with its whole distribution over actions (DAgger's labels,
soft). Each state then teaches every action's probability at once, at the cost of one
forward of the teacher, where a branch group needs a simulated branch per action.
Teachers with crash heads also label each action's crash probability, which a student
with a crash head fits (:class:`TeacherCrashLoss`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential
from torchrl.objectives import LossModule

from torchrl_grpo.objectives.loss_checks import check_crash_head_args, check_finite, require

__all__ = ["TeacherCrashLoss", "TeacherDistillLoss"]


class TeacherDistillLoss(LossModule):
    r"""``KL(teacher || policy)`` per state, averaged: ``sum_a p_T(a|s) (log p_T - log pi)``.

    Each row carries the teacher's logits for its state. The loss is the mean over rows
    of the KL divergence from the teacher's softmax to the policy's distribution; it is
    0 exactly when the policy gives every action the teacher's probability.

    Args:
        actor_network: the policy; its ``get_dist`` gives a categorical distribution
            (its ``logits`` are normalised log-probabilities). Its parameters are used
            as they are (not copied).

    Keys (change them with :meth:`set_keys`): ``teacher_logits`` (``"teacher_logits"``).

    Outputs: ``loss_distill``, and the diagnostics ``distill_agreement`` (the share of
    rows where the policy's most likely action is the teacher's) and
    ``teacher_entropy`` (the mean entropy of the teacher's distributions, in nats).

    Example:
        >>> import math
        >>> from torchrl_grpo.modules import make_discrete_actor
        >>> net = torch.nn.Linear(3, 2)
        >>> _ = torch.nn.init.zeros_(net.weight), torch.nn.init.zeros_(net.bias)
        >>> actor = make_discrete_actor(net, 2)  # every state: pi = (1/2, 1/2)
        >>> teacher = torch.tensor([[0.0, math.log(3.0)]])  # p_T = (1/4, 3/4)
        >>> data = TensorDict(observation=torch.ones(1, 3), teacher_logits=teacher,
        ...                   batch_size=[1])
        >>> out = TeacherDistillLoss(actor)(data)
        >>> expected = 0.25 * math.log(0.5) + 0.75 * math.log(1.5)
        >>> round(float(out["loss_distill"]), 6) == round(expected, 6)
        True
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`TeacherDistillLoss`, set with ``set_keys``.

        Attributes:
            teacher_logits: the teacher's logits of the row's state, ``[N, n_actions]``.
        """

        teacher_logits: NestedKey = "teacher_logits"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_distill", "distill_agreement", "teacher_entropy"]

    def __init__(self, actor_network: ProbabilisticTensorDictSequential) -> None:
        super().__init__()
        self.actor_network = actor_network

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        return list(dict.fromkeys([*self.actor_network.in_keys, self.tensor_keys.teacher_logits]))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The mean KL divergence over ``tensordict``'s rows (a flat batch)."""
        teacher = require(tensordict, self.tensor_keys.teacher_logits, "teacher_logits")
        log_pi = self.actor_network.get_dist(tensordict).logits
        if teacher.shape != log_pi.shape:
            raise ValueError(
                f"the teacher has {tuple(teacher.shape)} logits, the policy "
                f"{tuple(log_pi.shape)}: were they trained with the same actions?"
            )
        check_finite({"the teacher's logits": teacher, "the policy's log-probs": log_pi})
        log_teacher = torch.log_softmax(teacher, dim=-1)
        p_teacher = log_teacher.exp()
        kl = (p_teacher * (log_teacher - log_pi)).sum(-1)
        agreement = (log_pi.argmax(-1) == teacher.argmax(-1)).float().mean()
        entropy = -(p_teacher * log_teacher).sum(-1).mean()
        return TensorDict(
            loss_distill=kl.mean(),
            distill_agreement=agreement.detach(),
            teacher_entropy=entropy.detach(),
            batch_size=[],
        )


class TeacherCrashLoss(LossModule):
    r"""``coeff`` times the mean cross-entropy of a crash head to the teachers' crash odds.

    The teachers' crash heads give every action of every state a crash probability
    ``q_a = sigmoid(c_a)``. A student with a crash head
    (:class:`~torchrl_grpo.modules.CrashHead`) fits its own ``p_a`` to those soft labels,
    every action at once: ``-mean_a [q_a log p_a + (1 - q_a) log(1 - p_a)]``, averaged
    over rows. Its minimum is the labels' own entropy, reached exactly at ``p = q``; the
    diagnostic ``teacher_crash_excess`` is the loss less that minimum (a KL divergence,
    0 at the fit). A student that keeps the crash head can act with another
    ``crash_aversion`` than its teachers', and train on with ``algo.bootstrap=survival``.

    Args:
        head: a module whose ``crash_logits(observation)`` gives ``[*batch, n_actions]``
            logits (a :class:`~torchrl_grpo.modules.CrashHead`, or an ensemble of them);
            used as it is, not copied.

    Keyword Args:
        coeff: the weight of the term (``> 0``).

    Keys (change them with :meth:`set_keys`): ``observation`` (``"observation"``) and
    ``teacher_crash_logits`` (``"teacher_crash_logits"``).

    Outputs: ``loss_teacher_crash``, and the diagnostics ``teacher_crash_excess``
    (without ``coeff``) and ``teacher_crash_agreement`` (the share of states where the
    student's least likely action to crash is the teachers').

    Example:
        >>> from torchrl_grpo.modules import CrashHead
        >>> net = torch.nn.Linear(3, 4)
        >>> _ = torch.nn.init.zeros_(net.weight), torch.nn.init.zeros_(net.bias)
        >>> teacher = torch.zeros(1, 2)  # q = 1/2 for both actions: the student's own p
        >>> data = TensorDict(observation=torch.ones(1, 3), teacher_crash_logits=teacher,
        ...                   batch_size=[1])
        >>> out = TeacherCrashLoss(CrashHead(net, 2), coeff=1.0)(data)
        >>> round(float(out["loss_teacher_crash"]), 4), float(out["teacher_crash_excess"])
        (0.6931, 0.0)
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`TeacherCrashLoss`, set with ``set_keys``.

        Attributes:
            observation: the head's input.
            teacher_crash_logits: the teachers' crash logits of the row's state,
                ``[N, n_actions]``.
        """

        observation: NestedKey = "observation"
        teacher_crash_logits: NestedKey = "teacher_crash_logits"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_teacher_crash", "teacher_crash_excess", "teacher_crash_agreement"]

    def __init__(self, head: torch.nn.Module, *, coeff: float) -> None:
        check_crash_head_args(head, coeff, "the student needs model.crash_head=true")
        super().__init__()
        self.head = head
        self.coeff = coeff

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        return [self.tensor_keys.observation, self.tensor_keys.teacher_crash_logits]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The mean cross-entropy over ``tensordict``'s rows and actions (a flat batch)."""
        keys = self.tensor_keys
        observation = require(tensordict, keys.observation, "observation")
        teacher = require(tensordict, keys.teacher_crash_logits, "teacher_crash_logits")
        student = self.head.crash_logits(observation)
        if teacher.shape != student.shape:
            raise ValueError(
                f"the teachers have {tuple(teacher.shape)} crash logits, the student "
                f"{tuple(student.shape)}: were they trained with the same actions?"
            )
        check_finite({"the teachers' crash logits": teacher, "the student's": student})
        target = torch.sigmoid(teacher)
        bce = torch.nn.functional.binary_cross_entropy_with_logits(student, target)
        # The labels' own entropy: what no student can go under.
        floor = torch.nn.functional.binary_cross_entropy_with_logits(teacher, target)
        agreement = (student.argmin(-1) == teacher.argmin(-1)).float().mean()
        return TensorDict(
            loss_teacher_crash=self.coeff * bce,
            teacher_crash_excess=(bce - floor).detach(),
            teacher_crash_agreement=agreement.detach(),
            batch_size=[],
        )
