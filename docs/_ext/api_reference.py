"""API reference directives: a package's ``__all__``, read at every build.

``.. api-reference:: torchrl_grpo.envs`` documents the package: its docstring, a summary
table of every name of its ``__all__`` (``api-summary``), then every name, grouped into
classes, exceptions, functions and constants (autodoc for classes and functions; for
constants and type aliases, their ``#:`` comment or docstring from the module that
defines them). A name added to or removed from ``__all__`` appears on or leaves the page
without editing it.
"""

from __future__ import annotations

import importlib
import inspect
import sys
from types import ModuleType
from typing import Any

from docutils.statemachine import StringList
from sphinx.application import Sphinx
from sphinx.ext.autosummary import Autosummary
from sphinx.pycode import ModuleAnalyzer
from sphinx.util.docutils import SphinxDirective
from sphinx.util.inspect import stringify_signature

MAX_VALUE_CHARS = 100


def public_names(module: ModuleType) -> list[str]:
    """The module's ``__all__`` (an error if it has none)."""
    names = getattr(module, "__all__", None)
    if not names:
        raise ValueError(f"module {module.__name__!r} has no __all__")
    return list(names)


def kind_of(obj: Any) -> str:
    """``exception``, ``class``, ``function`` or ``data`` (constants, type aliases)."""
    if inspect.isclass(obj):
        return "exception" if issubclass(obj, BaseException) else "class"
    if inspect.isfunction(obj) or inspect.isbuiltin(obj):
        return "function"
    return "data"


def attribute_doc(module: ModuleType, name: str) -> list[str]:
    """The ``#:`` comment or docstring of a module-level name, where it is defined.

    A package re-exports names from its submodules: the documentation comment is in the
    submodule that assigns the name (the package itself is searched first).
    """
    obj = getattr(module, name)
    prefix = module.__name__ + "."
    candidates = [module] + [
        sub
        for modname, sub in sorted(sys.modules.items())
        if modname.startswith(prefix) and isinstance(sub, ModuleType)
    ]
    for candidate in candidates:
        if getattr(candidate, name, None) is not obj:
            continue
        try:
            docs = ModuleAnalyzer.for_module(candidate.__name__).find_attr_docs()
        except Exception:  # noqa: BLE001 (no source: nothing to find)
            continue
        lines = docs.get(("", name))
        if lines:
            return [line for line in lines if line is not None]
    return []


def first_paragraph(lines: list[str]) -> str:
    """The first paragraph of a doc comment, on one line (its markup left whole)."""
    paragraph: list[str] = []
    for line in lines:
        if not line.strip():
            if paragraph:
                break
            continue
        paragraph.append(line.strip())
    return " ".join(paragraph)


def value_repr(obj: Any) -> str | None:
    """A short repr of a constant's value, or None when it would be too long."""
    text = repr(obj).replace("\n", " ")
    return text if len(text) <= MAX_VALUE_CHARS else None


class ApiSummary(Autosummary):
    """An autosummary table of every name of a module's ``__all__``."""

    required_arguments = 1
    has_content = False
    option_spec = dict(Autosummary.option_spec)

    def run(self):
        """Fills the content with ``__all__`` and lets autosummary render the table."""
        module = importlib.import_module(self.arguments[0])
        names = public_names(module)
        if module.__file__:
            self.env.note_dependency(module.__file__)
        # Relative names: the page's automodule has set the current module.
        self.content = StringList(
            names,
            source=f"<api-summary {module.__name__}>",
        )
        return super().run()

    def get_items(self, names):
        """Autosummary's items; constants get their own doc comment, not their type's."""
        module = importlib.import_module(self.arguments[0])
        items = []
        for display_name, sig, summary, real_name in super().get_items(names):
            obj = getattr(module, display_name, None)
            if kind_of(obj) == "data":
                doc = attribute_doc(module, display_name)
                summary = first_paragraph(doc)
                sig = None
            items.append((display_name, sig, summary, real_name))
        return items


class ApiReference(SphinxDirective):
    """The whole API page of a package, generated from its ``__all__``."""

    required_arguments = 1
    has_content = False

    def run(self):
        """Builds the page's reStructuredText and parses it."""
        modname = self.arguments[0]
        module = importlib.import_module(modname)
        if module.__file__:
            self.env.note_dependency(module.__file__)
        groups: dict[str, list[str]] = {"class": [], "exception": [], "function": [], "data": []}
        for name in public_names(module):
            groups[kind_of(getattr(module, name))].append(name)

        lines = [f".. automodule:: {modname}", "", f".. api-summary:: {modname}", ""]
        titles = {
            "class": "Classes",
            "exception": "Exceptions",
            "function": "Functions",
            "data": "Constants and types",
        }
        for kind, names in groups.items():
            if not names:
                continue
            lines += [titles[kind], "-" * len(titles[kind]), ""]
            for name in names:
                if kind == "data":
                    lines += self.data_lines(module, name)
                elif kind == "function":
                    lines += [f".. autofunction:: {modname}.{name}", ""]
                else:
                    lines += [
                        f".. auto{kind}:: {modname}.{name}",
                        "   :members:",
                        "   :show-inheritance:",
                        "",
                    ]
        return self.parse_text_to_nodes(StringList(lines), allow_section_headings=True)

    @staticmethod
    def data_lines(module: ModuleType, name: str) -> list[str]:
        """A ``py:data`` entry with the value and the defining module's doc comment."""
        lines = [f".. py:data:: {name}", f"   :module: {module.__name__}"]
        value = value_repr(getattr(module, name))
        if value is not None:
            lines.append(f"   :value: {value}")
        lines.append("")
        lines += ["   " + line if line.strip() else "" for line in attribute_doc(module, name)]
        lines.append("")
        return lines


def init_signature(app, what, name, obj, options, signature, return_annotation):
    """A class whose base defines ``__new__(cls, *args, **kwargs)`` gets ``__init__``'s signature.

    TensorDict and torch base classes define such a ``__new__``, which autodoc prefers to
    ``__init__``: every module would read ``(*args, **kwargs)``.
    """
    if what not in ("class", "exception") or signature != "(*args, **kwargs)":
        return None
    init = getattr(obj, "__init__", None)
    if init is None or init is object.__init__:
        return None
    try:
        sig = inspect.signature(init)
    except (TypeError, ValueError):
        return None
    params = list(sig.parameters.values())[1:]  # drop self
    sig = sig.replace(parameters=params, return_annotation=inspect.Signature.empty)
    show = app.config.autodoc_typehints not in ("none", "description")
    return stringify_signature(sig, show_annotation=show), return_annotation


def setup(app: Sphinx) -> dict:
    """Registers ``api-summary`` and ``api-reference``."""
    app.setup_extension("sphinx.ext.autodoc")
    app.setup_extension("sphinx.ext.autosummary")
    app.add_directive("api-summary", ApiSummary)
    app.add_directive("api-reference", ApiReference)
    app.connect("autodoc-process-signature", init_signature)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}
