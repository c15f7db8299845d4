"""What a batch of trunk steps shows: the returns and crashes of the episodes that end in it.

The algorithms whose collector is TorchRL's ``Collector`` (PPO, teacher distillation)
get ``[W, T]`` batches of the workers' episodes, cut at batch boundaries. An episode's
return is carried across batches until its ``done``, and saved in checkpoints.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from torchrl_grpo.training.algos.base import Algorithm

__all__ = ["TrunkEpisodes"]


class TrunkEpisodes(Algorithm):
    """An :class:`Algorithm` whose ``collect/`` metrics are its trunks' finished episodes.

    Example:
        >>> from tensordict import TensorDict
        >>> algo = TrunkEpisodes.__new__(TrunkEpisodes)  # no loss needed for the metrics
        >>> algo.episode_return = None
        >>> done = torch.tensor([[False, True], [False, False]])
        >>> batch = TensorDict({("next", "reward"): torch.ones(2, 2), ("next", "done"): done,
        ...                     ("next", "crashed"): done, ("next", "speed"): torch.ones(2, 2)},
        ...                    batch_size=[2, 2])
        >>> m = algo.batch_metrics(batch)
        >>> m["collect/episode_return"], m["collect/crash_rate"], algo.episode_return.tolist()
        (2.0, 1.0, [0.0, 2.0])
    """

    #: Return of each worker's episode in progress, carried across batches.
    episode_return: torch.Tensor | None = None

    def batch_metrics(self, batch: TensorDictBase) -> dict[str, float]:
        """Returns and crashes of the episodes that ended in the batch."""
        data = batch if batch.ndim == 2 else batch.unsqueeze(0)
        reward = data.get(("next", "reward")).reshape(data.shape)
        done = data.get(("next", "done")).reshape(data.shape)
        crashed = data.get(("next", "crashed")).reshape(data.shape)
        acc = self.episode_return
        acc = torch.zeros(data.shape[0]) if acc is None else acc.clone()
        returns, crashes = [], []
        for t in range(data.shape[1]):
            acc += reward[:, t]
            for w in done[:, t].nonzero().flatten().tolist():
                returns.append(float(acc[w]))
                crashes.append(bool(crashed[w, t]))
                acc[w] = 0.0
        self.episode_return = acc
        out = {
            "collect/speed": float(data.get(("next", "speed")).float().mean()),
            "collect/reward": float(reward.float().mean()),
        }
        if returns:
            out["collect/episode_return"] = float(np.mean(returns))
            out["collect/crash_rate"] = float(np.mean(crashes))
            out["collect/episodes"] = float(len(returns))
        return out

    def state_dict(self) -> dict[str, Any]:  # noqa: D102
        acc = self.episode_return
        return {**super().state_dict(), "episode_acc": {} if acc is None else {"return": acc}}

    def load_state_dict(self, checkpoint: dict[str, Any], source: str = "") -> None:  # noqa: D102
        super().load_state_dict(checkpoint, source)
        self.episode_return = (checkpoint.get("episode_acc") or {}).get("return")
