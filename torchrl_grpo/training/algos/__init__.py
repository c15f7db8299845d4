"""The training algorithms, one file each, and their registry.

``grpo.py`` (``grpo_branch``, ``grpo_episode``), ``ppo.py`` (``ppo``) and ``teacher.py``
(``distill``: trained runs distilled into one policy) are built in.
Every other module of this package is imported with it, so a new algorithm is one
file here (a registered :class:`~torchrl_grpo.training.Algorithm` and its config
dataclass) plus its ``conf/algo/<name>.yaml``; see ``docs/training.md``.
"""

import importlib
import pkgutil

# An algorithm added as a file of this package registers itself when it is imported.
for _module in pkgutil.iter_modules(__path__, f"{__name__}."):
    importlib.import_module(_module.name)
