"""Sphinx configuration of the torchrl_grpo documentation.

Build (strict, offline): ``sphinx-build -W --keep-going -b html docs docs/_build/html``.
The config reference and the API summaries are generated from the code at every build
(``docs/_ext/``), so they cannot go stale.
"""

import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(ROOT))

project = "torchrl_grpo"
author = "torchrl_grpo contributors"
copyright = "torchrl_grpo contributors"
release = "0.1.0"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "config_reference",
    "api_reference",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_ext", "img", "Thumbs.db", ".DS_Store"]
templates_path: list[str] = []

# Markdown (MyST): heading anchors so that pages can link to sections (page.md#section).
myst_heading_anchors = 3
myst_enable_extensions = ["colon_fence"]

# API reference: Google-style docstrings; the members of each package's __all__.
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented"
# Docstrings of torch / TorchRL base classes are not this library's documentation.
autodoc_inherit_docstrings = False
autodoc_default_options: dict[str, bool] = {}
autosummary_generate = False

# No network at build time: no intersphinx, built-in theme.
html_theme = "alabaster"
html_title = "torchrl_grpo"
html_static_path: list[str] = []
html_theme_options = {"description": "GRPO on snapshottable simulators, built on TorchRL"}
