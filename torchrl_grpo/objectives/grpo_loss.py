"""GRPOLoss: the GRPO objective and its variants for any TorchRL probabilistic actor."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import (
    CompositeDistribution,
    ProbabilisticTensorDictSequential,
    composite_lp_aggregate,
)
from torch import distributions as d
from torchrl.objectives import LossModule

from torchrl_grpo.objectives.aggregation import (
    Aggregation,
    aggregate,
)
from torchrl_grpo.objectives.diagnostics import RATIO_DIAGNOSTICS, ratio_diagnostics
from torchrl_grpo.objectives.kl import KLEstimator, analytic_kl, kl_estimate
from torchrl_grpo.objectives.loss_checks import (
    behaviour_log_prob,
    check_finite,
    check_loss_args,
    per_step,
    require,
    sum_event,
)
from torchrl_grpo.objectives.loss_weights import batch_step_weights

__all__ = ["Aggregation", "GRPOLoss"]

_ADVANTAGE_HINT = " Compute it first, e.g. with GroupRelativeAdvantage."


class GRPOLoss(LossModule):
    r"""Group Relative Policy Optimisation loss for any ``ProbabilisticActor``.

    TorchRL's ``torchrl.objectives.llm.GRPOLoss`` needs an LLM wrapper; this one
    takes a plain actor (Categorical, Normal, TanhNormal, ...) and the branch-group
    data of this project: batch ``[R, G, T]``, ``[N, T]`` or flat ``[B]``, a boolean
    ``mask`` of valid steps, a precomputed ``advantage`` (see
    :class:`~torchrl_grpo.objectives.GroupRelativeAdvantage`). No critic.

    Per valid step, with ``rho = pi_theta(a|s) / pi_old(a|s)`` (``pi_old`` being the
    ``sample_log_prob`` entry) and advantage ``A``:

    .. math::

        \ell_{obj} = -\min(\rho A, \mathrm{clip}(\rho, 1 - \epsilon_{low}, 1 + \epsilon_{high}) A)

    with, if ``dual_clip=c``, ``max(., c A)`` applied inside the ``-`` when ``A < 0``
    (verl's ``clip_ratio_c``); ``\ell_{kl} = \beta\,KL`` to the reference policy;
    ``\ell_{ent} = -c_H H(\pi_\theta)``. Each term is aggregated over the valid steps
    by the same rule:

    - ``"dapo"`` / ``"bnpo"`` / ``"token_mean"``: mean over all valid steps;
    - ``"grpo"`` / ``"prompt_mean"``: mean over each trajectory's valid steps, then
      mean over trajectories (DeepSeekMath);
    - ``"dr_grpo"``: sum over valid steps divided by the constant
      ``n_trajectories * max_steps`` (Dr. GRPO).

    Trajectories are the rows of the last batch dimension (time) when the batch has
    two or more dimensions, and the ``(group_id, branch)`` pairs for a flat batch;
    a row without any valid step is padding, not a trajectory. Masked steps never
    reach the actor, so their content may be anything.

    With ``beta = 0``, a symmetric clip and ``"dapo"``, the objective equals
    TorchRL's ``ClipPPOLoss(actor, None, critic_coeff=None)`` on the same advantage.

    Args:
        actor_network: the policy; its ``get_dist`` gives the distribution.

    Keyword Args:
        clip_epsilon: ``eps`` for symmetric clipping, or ``(eps_low, eps_high)`` for
            DAPO's clip-higher, e.g. ``(0.2, 0.28)``. Schedulable buffers
            ``clip_epsilon_low`` / ``clip_epsilon_high``.
        dual_clip: the dual-clip bound ``c > 1`` on the loss of negative-advantage
            steps (verl ``clip_ratio_c``, typically 3.0); ``None`` disables it.
        kl_to_ref_coeff: ``beta``, the weight of the KL to the reference policy
            (TRL's ``beta``). ``None`` (default) builds no reference and emits no
            ``loss_kl``; a float, even 0.0, freezes a copy of the actor as the
            reference (``target_actor_network_params``, moved by
            :class:`~torchrl_grpo.objectives.ReferenceSync`).
        kl_estimator: ``"k1"``, ``"k2"``, ``"k3"`` (default, DeepSeekMath) or
            ``"analytic"`` (closed form, when the distribution has one). For the
            ``k`` estimators a ``ref_log_prob`` entry in the input, if present, is
            used instead of running the reference policy.
        entropy_bonus: whether to emit ``loss_entropy``.
        entropy_coeff: entropy weight (schedulable buffer).
        samples_mc_entropy: samples for the entropy of distributions with no closed
            form (TanhNormal).
        aggregation: see above. Defaults to ``"dapo"`` (TRL's default loss type).
        max_steps: Dr. GRPO's constant ``L``; defaults to the time dimension of the
            batch (longest trajectory for a flat batch). Set it to the branch
            horizon for a normaliser that is constant across batches.
        check_values: refuse a NaN or infinite advantage, behaviour, reference or
            policy log-prob on a valid step with a ``ValueError`` naming it (else the
            loss and every gradient are NaN). ``False`` skips the check, which costs
            about 0.5% of a forward + backward (1.005x on a ``[16, 8, 40]`` batch, one
            CPU thread: ``benchmarks/bench_loss_checks.py``). An attribute: switch it
            at any time. Arguments are always checked: a negative or non-finite
            ``kl_to_ref_coeff`` or ``entropy_coeff`` is a ``ValueError``.
        device: device of the coefficient buffers.

    Keys (change them with :meth:`set_keys`): ``advantage`` (``"advantage"``),
    ``action`` (``"action"``), ``sample_log_prob`` (the actor's log-prob key,
    ``"action_log_prob"`` for a ProbabilisticActor in TorchRL 0.14), ``ref_log_prob``
    (``"ref_log_prob"``, optional), ``mask`` (``"mask"``), ``group_id`` and
    ``branch`` (read only for trajectory aggregations of a flat batch).

    Outputs: ``loss_objective``, ``loss_entropy`` (if ``entropy_bonus``), ``loss_kl``
    (if ``kl_to_ref_coeff`` is set), and the diagnostics ``clip_fraction``,
    ``kl_approx`` (mean ``log pi_old - log pi_theta``), ``ESS`` (normalised effective
    sample size of the ratios, in (0, 1]), ``min_ratio``, ``mean_ratio``, ``max_ratio``,
    ``entropy``, ``kl_to_ref``, ``advantage_mean``, ``advantage_std``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> from torchrl_grpo.objectives import GRPOLoss
        >>> net = TensorDictModule(torch.nn.Linear(3, 4), ["observation"], ["logits"])
        >>> actor = ProbabilisticActor(
        ...     net, ["logits"], distribution_class=torch.distributions.Categorical,
        ...     return_log_prob=True)
        >>> data = actor(TensorDict(observation=torch.randn(2, 3, 5, 3), batch_size=[2, 3, 5]))
        >>> data["advantage"] = torch.randn(2, 3, 5, 1)
        >>> data["mask"] = torch.ones(2, 3, 5, dtype=torch.bool)
        >>> loss = GRPOLoss(actor, clip_epsilon=(0.2, 0.28), kl_to_ref_coeff=0.04)
        >>> out = loss(data.detach())
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        >>> float(out["loss_kl"].detach())  # the reference is still the policy
        0.0
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by :class:`GRPOLoss`, set with ``set_keys``.

        Attributes:
            advantage: per-step advantage, ``[*batch, 1]``.
            action: the action taken.
            sample_log_prob: log-prob of the action under the behaviour policy.
                Defaults to the actor's log-prob key.
            ref_log_prob: optional precomputed reference log-prob.
            mask: boolean, ``True`` on valid steps.
            group_id: integer id of the root (flat batches only).
            branch: integer branch index (flat batches only).
        """

        advantage: NestedKey = "advantage"
        action: NestedKey = "action"
        sample_log_prob: NestedKey | None = None
        ref_log_prob: NestedKey = "ref_log_prob"
        mask: NestedKey = "mask"
        group_id: NestedKey = "group_id"
        branch: NestedKey = "branch"

        def __post_init__(self) -> None:
            if self.sample_log_prob is None:
                # TorchRL's own default, which depends on tensordict's
                # composite log-prob aggregation setting
                aggregate = composite_lp_aggregate(nowarn=True)
                self.sample_log_prob = "sample_log_prob" if aggregate else "action_log_prob"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    actor_network: ProbabilisticTensorDictSequential
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams | None
    _schedulable_buffers = frozenset(
        {"clip_epsilon_low", "clip_epsilon_high", "dual_clip", "kl_to_ref_coeff", "entropy_coeff"}
    )

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        *,
        clip_epsilon: float | tuple[float, float] = 0.2,
        dual_clip: float | None = None,
        kl_to_ref_coeff: float | None = None,
        kl_estimator: KLEstimator = "k3",
        entropy_bonus: bool = True,
        entropy_coeff: float = 0.01,
        samples_mc_entropy: int = 1,
        aggregation: Aggregation = "dapo",
        max_steps: int | None = None,
        check_values: bool = True,
        device: torch.device | None = None,
    ) -> None:
        eps_low, eps_high = check_loss_args(
            aggregation=aggregation,
            kl_estimator=kl_estimator,
            clip_epsilon=clip_epsilon,
            dual_clip=dual_clip,
            max_steps=max_steps,
            samples_mc_entropy=samples_mc_entropy,
            kl_to_ref_coeff=kl_to_ref_coeff,
            entropy_coeff=entropy_coeff,
        )
        self.check_values = check_values
        self._in_keys = None
        self._out_keys = None
        super().__init__()
        has_reference = kl_to_ref_coeff is not None
        self.convert_to_functional(
            actor_network, "actor_network", create_target_params=has_reference
        )
        # A frozen reference is a valid setup, not a forgotten target updater:
        # silence TorchRL's "no updater associated" warning.
        self._has_update_associated["actor_network"] = True
        if device is None:
            device = next(
                iter(self.actor_network_params.values(True, True)), torch.zeros(())
            ).device
        self.register_coeff_buffer("clip_epsilon_low", eps_low, device=device)
        self.register_coeff_buffer("clip_epsilon_high", eps_high, device=device)
        self.register_coeff_buffer("dual_clip", dual_clip, device=device)
        self.register_coeff_buffer("kl_to_ref_coeff", kl_to_ref_coeff, device=device)
        self.register_coeff_buffer("entropy_coeff", entropy_coeff, device=device)
        self.kl_estimator = kl_estimator
        self.entropy_bonus = entropy_bonus
        self.samples_mc_entropy = samples_mc_entropy
        self.aggregation = aggregation
        self.max_steps = max_steps
        log_prob_keys = getattr(actor_network, "log_prob_keys", None)
        if log_prob_keys:
            if len(log_prob_keys) > 1:
                raise ValueError(
                    f"GRPOLoss supports a single action head; the actor has log-prob keys "
                    f"{log_prob_keys}."
                )
            self.set_keys(
                sample_log_prob=log_prob_keys[0], action=actor_network.dist_sample_keys[0]
            )

    # ------------------------------------------------------------------ keys
    def _set_in_keys(self) -> None:
        k = self.tensor_keys
        keys = [*self.actor_network.in_keys, k.action, k.sample_log_prob, k.advantage, k.mask]
        self._in_keys = list(dict.fromkeys(keys))

    @property
    def in_keys(self) -> list[NestedKey]:  # noqa: D102
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values: list[NestedKey]) -> None:
        self._in_keys = values

    @property
    def out_keys(self) -> list[NestedKey]:  # noqa: D102
        if self._out_keys is None:
            keys = ["loss_objective"]
            if self.entropy_bonus:
                keys += ["loss_entropy", "entropy"]
            if self.kl_to_ref_coeff is not None:
                keys += ["loss_kl", "kl_to_ref"]
            self._out_keys = [*keys, *RATIO_DIAGNOSTICS]
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values: list[NestedKey]) -> None:
        self._out_keys = values

    def _forward_value_estimator_keys(self, **kwargs: object) -> None:
        # no value estimator in a critic-free loss: only refresh the input keys
        self._set_in_keys()

    # --------------------------------------------------------------- forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the loss terms and diagnostics over the valid steps of ``tensordict``."""
        keys = self.tensor_keys
        batch_size = tensordict.batch_size
        mask = require(tensordict, keys.mask, "mask")
        mask = per_step(mask, batch_size, keys.mask)
        if mask.dtype != torch.bool:
            raise ValueError(f"{keys.mask!r} must be boolean, got dtype {mask.dtype}.")
        all_valid = bool(mask.all())
        if all_valid:
            steps = tensordict
            valid_idx = None
        else:
            valid_idx = mask.nonzero().squeeze(-1)
            if not valid_idx.numel():
                raise ValueError(f"{keys.mask!r} marks no valid step: nothing to optimise.")
            # keep masked steps away from the actor: their observations may be
            # garbage, and NaN activations poison gradients even when zeroed later
            needed = [*self.in_keys, keys.ref_log_prob, keys.group_id, keys.branch]
            steps = tensordict.select(*needed, strict=False).reshape(-1)[valid_idx]
        n_batch = len(steps.batch_size)

        advantage = per_step(
            require(steps, keys.advantage, "advantage", hint=_ADVANTAGE_HINT),
            steps.batch_size,
            keys.advantage,
        )
        prev_log_prob = behaviour_log_prob(steps, keys.sample_log_prob)
        dist = self._dist(steps, self.actor_network_params)
        action = require(steps, keys.action, "action")
        log_prob = per_step(sum_event(dist.log_prob(action), n_batch), steps.batch_size, "log-prob")
        if self.check_values:
            check_finite(
                {
                    repr(keys.advantage): advantage,
                    repr(keys.sample_log_prob): prev_log_prob,
                    repr(keys.ref_log_prob): steps.get(keys.ref_log_prob, None),
                    "the log-prob of the current policy": log_prob,
                }
            )
        weights = batch_step_weights(
            tensordict, mask, valid_idx, self.aggregation, self.max_steps, keys
        )

        log_weight = log_prob - prev_log_prob
        log_weight_clip = log_weight.clamp(
            (-self.clip_epsilon_low).log1p(), self.clip_epsilon_high.log1p()
        )
        ratio = log_weight.exp()
        gain = torch.minimum(ratio * advantage, log_weight_clip.exp() * advantage)
        if self.dual_clip is not None:
            gain = torch.where(advantage < 0, torch.maximum(gain, self.dual_clip * advantage), gain)
        out = {"loss_objective": -aggregate(gain, weights)}

        diag = {}
        if self.entropy_bonus:
            entropy = per_step(self._entropy(dist, n_batch), steps.batch_size, "entropy")
            out["loss_entropy"] = -self.entropy_coeff * aggregate(entropy, weights)
            diag["entropy"] = entropy
        if self.kl_to_ref_coeff is not None:
            kl = self._kl_to_reference(steps, dist, log_prob, n_batch)
            out["loss_kl"] = self.kl_to_ref_coeff * aggregate(kl, weights)
            diag["kl_to_ref"] = kl

        for name, value in diag.items():
            out[name] = value.detach().mean()
        out.update(ratio_diagnostics(log_weight, log_weight_clip, advantage))
        return TensorDict(out, batch_size=[])

    # ------------------------------------------------------------- helpers
    def _dist(self, steps: TensorDictBase, params: TensorDictBase) -> d.Distribution:
        with params.to_module(self.actor_network, preserve_module_state=False):
            dist = self.actor_network.get_dist(steps)
        if isinstance(dist, CompositeDistribution):
            raise NotImplementedError("GRPOLoss supports single-head (non-composite) actors.")
        return dist

    def _entropy(self, dist: d.Distribution, n_batch: int) -> torch.Tensor:
        try:
            entropy = dist.entropy()
        except NotImplementedError:
            entropy = None
        if entropy is None or not bool(torch.isfinite(entropy).all()):
            # no closed form (TanhNormal): Monte-Carlo, reparameterised when possible
            n = (self.samples_mc_entropy,)
            sample = dist.rsample(n) if dist.has_rsample else dist.sample(n)
            entropy = -dist.log_prob(sample).mean(0)
        return sum_event(entropy, n_batch)

    def _kl_to_reference(
        self, steps: TensorDictBase, dist: d.Distribution, log_prob: torch.Tensor, n_batch: int
    ) -> torch.Tensor:
        if self.kl_estimator == "analytic":
            with torch.no_grad():
                ref_dist = self._dist(steps, self.target_actor_network_params)
            kl = sum_event(analytic_kl(dist, ref_dist), n_batch)
            return per_step(kl, steps.batch_size, "analytic KL")
        ref_log_prob = steps.get(self.tensor_keys.ref_log_prob, None)
        if ref_log_prob is None:
            with torch.no_grad():
                ref_dist = self._dist(steps, self.target_actor_network_params)
                ref_log_prob = ref_dist.log_prob(steps.get(self.tensor_keys.action))
        ref_log_prob = per_step(
            sum_event(ref_log_prob, n_batch), steps.batch_size, self.tensor_keys.ref_log_prob
        )
        return kl_estimate(log_prob, ref_log_prob.detach(), self.kl_estimator)
