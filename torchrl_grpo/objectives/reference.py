"""Keeping the reference policy of a :class:`GRPOLoss` in step with the policy.

A :class:`~torchrl_grpo.objectives.GRPOLoss` built with a KL coefficient holds the
reference parameters in ``target_actor_network_params``, a frozen copy of the
actor taken when the loss is built. Without an updater the reference stays
frozen. :class:`ReferenceSync` moves it the way TRL's ``sync_ref_model`` does.
"""

from __future__ import annotations

from torch import Tensor
from torchrl.objectives import LossModule
from torchrl.objectives.utils import TargetNetUpdater

__all__ = ["ReferenceSync"]


class ReferenceSync(TargetNetUpdater):
    """Every ``ref_model_sync_steps`` calls to :meth:`step`, mix the policy into the reference.

    The update is ``ref <- alpha * policy + (1 - alpha) * ref`` with ``alpha =
    ref_model_mixup_alpha``, TRL's ``SyncRefModelCallback`` (option names
    ``ref_model_sync_steps``, ``ref_model_mixup_alpha``):

    - ``ref_model_mixup_alpha=1.0``: a hard copy every N updates;
    - ``ref_model_sync_steps=1`` and a small alpha: an exponential moving average;
    - no ``ReferenceSync`` at all: the reference stays frozen at the start.

    Call :meth:`step` after each optimiser step. Building the updater copies the
    current policy into the reference (as every TorchRL target updater does), so
    build it together with the loss.

    Args:
        loss_module: a :class:`~torchrl_grpo.objectives.GRPOLoss` with a KL term.

    Keyword Args:
        ref_model_sync_steps: updates between two syncs (TRL's default 512).
        ref_model_mixup_alpha: weight of the policy in the mix (TRL's default 0.6).

    Example:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ProbabilisticActor
        >>> from torchrl_grpo.objectives import GRPOLoss, ReferenceSync
        >>> net = TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["logits"])
        >>> categorical = torch.distributions.Categorical
        >>> actor = ProbabilisticActor(net, ["logits"], distribution_class=categorical)
        >>> loss = GRPOLoss(actor, kl_to_ref_coeff=0.04)
        >>> sync = ReferenceSync(loss, ref_model_sync_steps=2, ref_model_mixup_alpha=1.0)
        >>> with torch.no_grad():
        ...     _ = loss.actor_network_params.apply(lambda p: p.add_(1.0))
        >>> sync.step()  # 1 update: not yet
        >>> bool((loss.target_actor_network_params == loss.actor_network_params).all())
        False
        >>> sync.step()  # 2 updates: hard copy
        >>> bool((loss.target_actor_network_params == loss.actor_network_params).all())
        True
    """

    def __init__(
        self,
        loss_module: LossModule,
        *,
        ref_model_sync_steps: int = 512,
        ref_model_mixup_alpha: float = 0.6,
    ) -> None:
        # LossModule.__getattr__ falls back to the live parameters for a missing
        # target, so look the reference up among the registered modules
        if loss_module._modules.get("target_actor_network_params") is None:
            raise ValueError(
                "the loss has no reference policy (target_actor_network_params): build it "
                "with a kl_to_ref_coeff to use a ReferenceSync."
            )
        if ref_model_sync_steps < 1:
            raise ValueError(f"ref_model_sync_steps must be >= 1, got {ref_model_sync_steps}.")
        if not 0.0 < ref_model_mixup_alpha <= 1.0:
            raise ValueError(
                f"ref_model_mixup_alpha must be in (0, 1], got {ref_model_mixup_alpha}."
            )
        super().__init__(loss_module)
        self.ref_model_sync_steps = int(ref_model_sync_steps)
        self.ref_model_mixup_alpha = float(ref_model_mixup_alpha)
        self.counter = 0

    def step(self) -> None:
        """Counts one policy update and syncs the reference when the count is due."""
        self.counter += 1
        if self.counter % self.ref_model_sync_steps == 0:
            super().step()

    def _step(self, p_source: Tensor, p_target: Tensor) -> None:
        p_target.data.lerp_(p_source.data, self.ref_model_mixup_alpha)
