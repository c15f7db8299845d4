"""The key renaming of the keyed tensordict modules that are not losses.

TorchRL's losses rename their keys with ``LossModule.set_keys``. The modules here that
run before a loss (:class:`~torchrl_grpo.objectives.HorizonBootstrap`,
:class:`~torchrl_grpo.objectives.survival.TailSurvival`) declare their keys the same way, in an
``_AcceptedKeys`` dataclass, and share this ``set_keys``.
"""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any, Self

from tensordict import NestedKey
from tensordict.nn import TensorDictModuleBase

__all__ = ["KeyedModule"]


class KeyedModule(TensorDictModuleBase):
    """A tensordict module whose keys are the fields of its ``_AcceptedKeys`` dataclass.

    Subclasses define ``_AcceptedKeys`` and call ``super().__init__()``, which sets
    ``tensor_keys`` to its defaults.

    Example:
        >>> from dataclasses import dataclass
        >>> class Copy(KeyedModule):
        ...     @dataclass
        ...     class _AcceptedKeys:
        ...         source: NestedKey = "x"
        ...     in_keys, out_keys = [], []
        >>> Copy().set_keys(source="y").tensor_keys.source
        'y'
    """

    _AcceptedKeys: Any

    def __init__(self) -> None:
        super().__init__()
        self.tensor_keys = self._AcceptedKeys()

    def set_keys(self, **keys: NestedKey) -> Self:
        """Renames the keys read and written, e.g. ``set_keys(mask="valid")``.

        Raises:
            ValueError: for a name that is not one of the accepted keys.
        """
        accepted = sorted(f.name for f in fields(self._AcceptedKeys))
        unknown = sorted(set(keys) - set(accepted))
        if unknown:
            raise ValueError(
                f"{unknown} are not accepted keys of {type(self).__name__}: {accepted}."
            )
        self.tensor_keys = replace(self.tensor_keys, **keys)
        return self
