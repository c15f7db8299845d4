"""A policy sent to branch workers: pickled once per rollout, its draws seeded per branch.

Workers that run whole branches (:mod:`~torchrl_grpo.branching.worker_branches`) each hold a
copy of the policy. The parent pickles it at the start of a rollout
(:func:`pack_policy`); each worker unpickles it (:class:`PolicyCopy`) and, before
each branch, seeds every random source the copy draws from, from the rollout's base
seeds and the branch's index. A branch's samples then depend on neither the worker
it runs on, nor W, nor timing.

The random sources are torch's global generator (what ``torch.distributions``
samples from) and the ``torch.Generator`` objects the policy holds (e.g.
:class:`~torchrl_grpo.modules.RandomPolicy`'s): their base seeds are drawn, once per
rollout, from the parent's global generator and from the policy's own generators, so
``torch.manual_seed`` and a policy's seed keep their meaning. A policy that holds
tensors or generators off the CPU, numpy / ``random`` generators (whose copies
would repeat one another's draws) or an env (a planner's) is not packed:
:func:`pack_policy` returns ``None`` and the rollout runs in the parent.
"""

from __future__ import annotations

import io
import logging
import pickle
import random
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from torchrl_grpo.branching.direct_actor import ProbedPolicy
from torchrl_grpo.branching.seeding import branch_seed

logger = logging.getLogger(__name__)

__all__ = ["PackedPolicy", "PolicyCopy", "pack_policy"]

_SEED_HIGH = 2**62
# Random sources a copy cannot reseed: copies would repeat the same draws.
_UNSEEDABLE = (np.random.Generator, np.random.RandomState, random.Random)


class _NotPortable(Exception):
    """The policy holds something a CPU worker cannot use as its own copy."""


@dataclass
class PackedPolicy:
    """A pickled policy and the base seeds of one rollout.

    Attributes:
        blob: the pickle; each ``torch.Generator`` the policy holds is left out
            (a persistent id), and the copy gets a fresh one.
        seeds: the base seed of torch's global generator, then one per generator of
            the policy, in the order of the pickle.
    """

    blob: bytes
    seeds: list[int]


class _Packer(pickle.Pickler):
    def __init__(self, file: io.BytesIO) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.generators: dict[int, tuple[int, torch.Generator]] = {}

    def persistent_id(self, obj: Any) -> Any:
        if isinstance(obj, torch.Tensor) and obj.device.type != "cpu":
            raise _NotPortable(f"a tensor on {obj.device}")
        if isinstance(obj, torch.Generator):
            if obj.device.type != "cpu":
                raise _NotPortable(f"a generator on {obj.device}")
            index, _ = self.generators.setdefault(id(obj), (len(self.generators), obj))
            return ("generator", index)
        if isinstance(obj, _UNSEEDABLE):
            raise _NotPortable(f"a {type(obj).__name__}")
        if isinstance(obj, EnvBase):
            # A policy that steps an env of its own (a planner): copies would start or
            # share its simulators and workers.
            raise _NotPortable(f"an env ({type(obj).__name__})")
        return None


class _Unpacker(pickle.Unpickler):
    def __init__(self, file: io.BytesIO) -> None:
        super().__init__(file)
        self.generators: dict[int, torch.Generator] = {}

    def persistent_load(self, pid: Any) -> Any:
        kind, index = pid
        if kind != "generator":
            raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")
        return self.generators.setdefault(index, torch.Generator())


def pack_policy(policy: Any) -> PackedPolicy | None:
    """Pickle ``policy`` for CPU workers and draw this rollout's base seeds; ``None`` if it can't.

    Each call draws one number from torch's global generator and one from each
    generator of the policy, so that successive rollouts sample differently.

    Example:
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> packed = pack_policy(RandomPolicy(seed=0))
        >>> len(packed.seeds)  # torch's global generator and the policy's own
        2
        >>> pack_policy(lambda td: td) is None  # a lambda does not pickle
        True
    """
    buffer = io.BytesIO()
    packer = _Packer(buffer)
    try:
        packer.dump(policy)
    except Exception as err:  # noqa: BLE001 - any failure means: run it in the parent
        logger.debug("the policy stays in the parent process: %s", err)
        return None
    generators = [g for _, g in sorted(packer.generators.values(), key=lambda item: item[0])]
    seeds = [int(torch.randint(_SEED_HIGH, ()))]
    seeds += [int(torch.randint(_SEED_HIGH, (), generator=g)) for g in generators]
    return PackedPolicy(buffer.getvalue(), seeds)


class PolicyCopy:
    """A worker's copy of a packed policy, its random sources seeded per branch.

    Args:
        packed: what :func:`pack_policy` returned in the parent.
        direct: let a plain categorical actor run through its exact direct path
            (:class:`~torchrl_grpo.branching.direct_actor.ProbedPolicy`).

    Example:
        >>> from tensordict import TensorDict
        >>> from torchrl_grpo.modules import RandomPolicy
        >>> copy = PolicyCopy(pack_policy(RandomPolicy(seed=0)))
        >>> td = TensorDict(observation=torch.zeros(1, 5, 5), batch_size=[1])
        >>> draws = []
        >>> for branch in (3, 4, 3):
        ...     copy.seed_branch(branch)
        ...     draws.append(copy(td.clone())["action"].item())
        >>> draws[0] == draws[2]
        True
    """

    def __init__(self, packed: PackedPolicy, *, direct: bool = True) -> None:
        unpacker = _Unpacker(io.BytesIO(packed.blob))
        self.policy = unpacker.load()
        # A plain categorical actor runs without its TensorDict modules where that is
        # bitwise the same (direct_actor): about 0.3 ms less per merge-v0 step.
        self.call = ProbedPolicy(self.policy) if direct else self.policy
        self.generators = [unpacker.generators[i] for i in sorted(unpacker.generators)]
        self.seeds = packed.seeds

    def seed_branch(self, index: int) -> None:
        """Seed torch's global generator and the policy's generators for branch ``index``."""
        # The CPU generator only: torch.manual_seed also seeds the accelerators' (100+ us).
        torch.default_generator.manual_seed(branch_seed(self.seeds[0], index, 0))
        for generator, seed in zip(self.generators, self.seeds[1:], strict=True):
            generator.manual_seed(branch_seed(seed, index, 0))

    def __call__(self, td: TensorDictBase) -> TensorDictBase | None:
        """Run the policy on ``td``."""
        return self.call(td)
