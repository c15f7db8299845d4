"""``config-reference`` directive: the Hydra config reference, generated at every build.

The tables come from the code and the YAML files, never from hand-written text:

* the schemas are the dataclasses registered in Hydra's ConfigStore by
  :func:`torchrl_grpo.training.config.register_configs` (``base_<group>`` in each group,
  ``base_config`` and ``base_evaluate`` at the top; the ``algo`` group's schemas are in
  ``torchrl_grpo/training/algos/``, one file per algorithm); every key's type comes from the
  dataclass's type hints, its default from :func:`dataclasses.fields` (``str`` enums list
  their choices, nested dataclasses such as ``rollout.ray`` are expanded);
* a key's meaning is the inline comment of that key in ``conf/<group>/*.yaml`` (the
  most common one over the group's files; among equals, the default option's), else the
  docstring of its enum or nested dataclass; every option file of a group gets a column
  with the values it sets, and its leading comment as a description.

The page that holds the directive depends on every module of ``torchrl_grpo/training/``
and on every file under ``conf/``, and is re-read at every build (``env-get-outdated``), so an
incremental build cannot serve a stale reference.

:func:`generate_rst` is the generator on its own (no Sphinx needed):
``python docs/_ext/config_reference.py`` prints the reference as reStructuredText.
"""

from __future__ import annotations

import importlib
import inspect
import re
import typing
from pathlib import Path
from typing import Any

from config_schema import (
    SCHEMA_MODULE,
    file_schema,
    flatten,
    format_value,
    registered_schemas,
    schema_keys,
)
from config_yaml import YamlFile, read_yaml
from rst_text import inline, list_table, literal, section

ROOT = Path(__file__).resolve().parents[2]
CONF_DIR = ROOT / "conf"
# Where the schema classes are documented in the API reference (if they are listed there).
API_MODULE = "torchrl_grpo.training"


# --------------------------------------------------------------------------- RST output


def schema_ref(schema: type) -> str:
    """A link to the schema's API entry when the API reference lists it, else a literal."""
    api = importlib.import_module(API_MODULE)
    if schema.__name__ in getattr(api, "__all__", ()):
        return f":class:`~{API_MODULE}.{schema.__name__}`"
    return literal(schema.__name__)


def schema_table(
    schema: type,
    comment_of: typing.Callable[[str], str | None],
    skip: set[str] = frozenset(),
    group_options: dict[str, str] | None = None,
) -> list[str]:
    """Key, type, default and meaning of every key of a schema.

    ``group_options``: the keys that are config groups chosen in the file's defaults list
    (``env: highway_fast``), with the chosen option.
    """
    group_options = group_options or {}
    rows = []
    for key in schema_keys(schema):
        if key.key.split(".")[0] in skip:
            continue
        if key.nested:
            type_cell = literal(key.type)
            if key.key in group_options:
                default_cell = f"group option {literal(group_options[key.key])}"
                comment = comment_of(f"defaults.{key.key}")
                meaning = inline(comment) if comment else key.doc
                rows.append([literal(key.key), type_cell, default_cell, meaning])
                continue
            default_cell = "see below" if not key.required else "required"
        else:
            type_cell = literal(key.type)
            if key.choices:
                type_cell += ": one of " + ", ".join(literal(c) for c in key.choices)
            if key.aliases:
                type_cell += (
                    " (also "
                    + ", ".join(
                        f"{literal(alias)} for {literal(choice)}"
                        for alias, choice in key.aliases.items()
                    )
                    + ")"
                )
            default_cell = "required" if key.required else literal(key.default)
        comment = comment_of(key.key)
        meaning = inline(comment) if comment else key.doc  # the docstring is RST already
        rows.append([literal(key.key), type_cell, default_cell, meaning])
    return list_table(["key", "type", "default", "meaning"], rows, "config-schema", "20 25 15 40")


def options_table(schema: type, files: list[YamlFile], prefix: str) -> list[str]:
    """The value each option file sets for each key (a dash: not set)."""
    flats = []
    for file in files:
        if file.global_package:
            root = importlib.import_module(SCHEMA_MODULE).Config
            flats.append(flatten(file.values, root))
        else:
            flats.append(flatten(file.values, schema))
    order = [prefix + k.key for k in schema_keys(schema) if not k.nested]
    keys = [k for k in order if any(k in flat for flat in flats)]
    for flat in flats:
        keys.extend(k for k in flat if k not in keys)
    rows = [
        [literal(key)] + [literal(format_value(flat[key])) if key in flat else "" for flat in flats]
        for key in keys
    ]
    header = ["key"] + [literal(file.option) for file in files]
    return list_table(header, rows, "config-options")


def _relative(path: Path) -> str:
    try:
        return str(path.relative_to(ROOT))
    except ValueError:
        return str(path)


def _docstring_paragraphs(obj: Any) -> str:
    """The docstring of a schema up to its first Google-style section (``Example:``)."""
    doc = inspect.getdoc(obj) or ""
    kept = []
    for paragraph in doc.split("\n\n"):
        if re.match(r"^(Example|Examples|Args|Returns|Raises|Note)s?:", paragraph):
            break
        kept.append(paragraph)
    return "\n\n".join(kept)


def _comment_lookup(files: list[YamlFile], prefix: str) -> typing.Callable[[str], str | None]:
    """A key's meaning: its most common inline comment over the files (ties: first file)."""

    def comment_of(key: str) -> str | None:
        found = [file.comments.get((prefix if file.global_package else "") + key) for file in files]
        found = [comment for comment in found if comment]
        if not found:
            return None
        return max(found, key=found.count)  # max keeps the first of equal counts

    return comment_of


def generate_rst(conf_dir: Path = CONF_DIR) -> str:
    """The config reference as reStructuredText (sections start at level ``-``)."""
    module = importlib.import_module(SCHEMA_MODULE)
    top, groups = registered_schemas()
    config_file = read_yaml(conf_dir / "config.yaml")
    group_defaults: dict[str, str] = {}
    for entry in config_file.defaults:
        if isinstance(entry, dict):
            group_defaults.update({str(k): str(v) for k, v in entry.items()})
    group_order = [g for g in group_defaults if g in groups]
    group_order += sorted(g for g in groups if g not in group_order)

    out: list[str] = []
    out += [_docstring_paragraphs(module), ""]
    out += [
        "Generated at every build from the dataclasses of "
        f"{literal(_relative(Path(module.__file__)))} and "
        f"{literal(_relative(Path(module.__file__).parent / 'algos'))} (types and defaults, "
        "as registered "
        "in Hydra's ConfigStore) and from the YAML files of "
        f"{literal(_relative(conf_dir))} (values and the inline comment of every key). "
        "Set a key on the command line with "
        f"{literal('python scripts/train.py group.key=value')}, pick an option with "
        f"{literal('group=option')}.",
        "",
    ]

    # ---- the groups and their defaults
    out += section("Config groups", "-")
    rows = []
    for group in group_order:
        options = sorted(p.stem for p in (conf_dir / group).glob("*.yaml"))
        default = group_defaults.get(group, "")
        schemas = ", ".join(schema_ref(tp) for tp in groups[group].values())
        rows.append(
            [
                f"`{group}`_",
                literal(default) if default else "",
                ", ".join(literal(o) for o in options),
                schemas,
                inline(config_file.comments.get(f"defaults.{group}", "")),
            ]
        )
    out += list_table(["group", "default", "options", "schema", "comment"], rows, "config-groups")

    # ---- the top-level keys of conf/config.yaml
    config_schema = top.get("base_config")
    if config_schema is not None:
        out += section("Top-level keys", "-")
        out += [
            f"Schema {schema_ref(config_schema)}, file {literal('conf/config.yaml')}: "
            + inline(config_file.description),
            "",
        ]
        out += schema_table(
            config_schema, _comment_lookup([config_file], ""), skip=set(group_order)
        )

    # ---- every group
    for group in group_order:
        files = {p.stem: read_yaml(p) for p in sorted((conf_dir / group).glob("*.yaml"))}
        default = group_defaults.get(group)
        ordered = sorted(files.values(), key=lambda f: (f.option != default, f.option))
        out += section(literal(group), "-")
        out += [
            f"Options: {literal(f'conf/{group}/<option>.yaml')}"
            + (f", default {literal(default)}" if default else "")
            + ".",
            "",
        ]
        for name, schema in groups[group].items():
            users = [f for f in ordered if file_schema(f, groups[group], files) == name]
            prefix = f"{group}."
            if len(groups[group]) > 1:
                out += section(f"{literal(name)} ({schema.__name__})", "~")
            out += [
                f"Schema {schema_ref(schema)} (registered as {literal(f'{group}/{name}')}).",
                "",
            ]
            doc = _docstring_paragraphs(schema)
            if doc:
                out += [doc, ""]
            out += schema_table(schema, _comment_lookup(users, prefix))
            if users:
                out += ["Options:", ""]
                for file in users:
                    desc = inline(file.description) if file.description else ""
                    out.append(f"* {literal(file.option)}: {desc}".rstrip())
                out.append("")
                if any(f.global_package for f in users):
                    out += [
                        "These files are " + literal("# @package _global_") + ": they set keys "
                        "of other groups too, so their keys are full paths.",
                        "",
                    ]
                out += [
                    "Values set by each option (a dash: not set, so the schema's default or "
                    "the value of the option it builds on):",
                    "",
                ]
                global_prefix = prefix if any(f.global_package for f in users) else ""
                out += options_table(schema, users, global_prefix)

    # ---- scripts/evaluate.py
    eval_schema = top.get("base_evaluate")
    eval_path = conf_dir / "evaluate.yaml"
    if eval_schema is not None and eval_path.exists():
        eval_file = read_yaml(eval_path)
        out += section(f"{literal('scripts/evaluate.py')}", "-")
        out += [
            f"Schema {schema_ref(eval_schema)}, file {literal('conf/evaluate.yaml')}: "
            + inline(eval_file.description),
            "",
        ]
        eval_groups: dict[str, str] = {}
        for entry in eval_file.defaults:
            if isinstance(entry, dict):
                eval_groups.update({str(k): str(v) for k, v in entry.items()})
        out += schema_table(
            eval_schema, _comment_lookup([eval_file], ""), group_options=eval_groups
        )
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------- Sphinx


def setup(app: Any) -> dict:
    """Registers the ``config-reference`` directive."""
    from sphinx.util.docutils import SphinxDirective

    class ConfigReference(SphinxDirective):
        """Inserts the generated config reference (sections start at level ``-``)."""

        has_content = False

        def run(self) -> list:
            module = importlib.import_module(SCHEMA_MODULE)
            for path in sorted(Path(module.__file__).parent.rglob("*.py")):
                self.env.note_dependency(str(path))
            for path in sorted(CONF_DIR.rglob("*.yaml")):
                self.env.note_dependency(str(path))
            docs = getattr(self.env, "config_reference_docs", set())
            docs.add(self.env.docname)
            self.env.config_reference_docs = docs
            return self.parse_text_to_nodes(generate_rst(), allow_section_headings=True)

    def outdated(app, env, added, changed, removed):
        # Always re-read the page: a new YAML file is no dependency yet.
        return [d for d in getattr(env, "config_reference_docs", ()) if d in env.found_docs]

    def purge(app, env, docname):
        getattr(env, "config_reference_docs", set()).discard(docname)

    def merge(app, env, docnames, other):
        docs = getattr(env, "config_reference_docs", set())
        docs |= getattr(other, "config_reference_docs", set()) & set(docnames)
        env.config_reference_docs = docs

    app.add_directive("config-reference", ConfigReference)
    app.connect("env-get-outdated", outdated)
    app.connect("env-purge-doc", purge)
    app.connect("env-merge-info", merge)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}


if __name__ == "__main__":
    print(generate_rst())
