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

import dataclasses
import enum
import importlib
import inspect
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
CONF_DIR = ROOT / "conf"
SCHEMA_MODULE = "torchrl_grpo.training.config"
# The schemas are dataclasses of the training package (the algorithms' in their files).
SCHEMA_PACKAGE = "torchrl_grpo.training"
# Where the schema classes are documented in the API reference (if they are listed there).
API_MODULE = "torchrl_grpo.training"
# YAML keys that belong to Hydra, not to the schemas.
HYDRA_KEYS = ("defaults", "hydra")
OMEGACONF_MISSING = "???"


# --------------------------------------------------------------------------- YAML files


@dataclass
class YamlFile:
    """One file of ``conf/``: its values and inline comments, by dotted key."""

    path: Path
    option: str
    description: str
    global_package: bool
    defaults: list[Any]
    values: dict[str, Any]
    comments: dict[str, str] = field(default_factory=dict)


_KEY_LINE = re.compile(r"^(?P<indent>\s*)(?P<dash>-\s+)?(?P<key>[A-Za-z_][\w.-]*)\s*:(?P<rest>.*)$")
_COMMENT = re.compile(r"(?:^|\s)#\s?(?P<comment>.*)$")


def _split_comment(rest: str) -> str | None:
    """The inline comment of a line's value part, or None (values here hold no ``#``)."""
    match = _COMMENT.search(rest)
    return match.group("comment").strip() if match else None


def read_yaml_comments(text: str) -> tuple[str, bool, dict[str, str]]:
    """Parses a Hydra YAML file's comments.

    Returns:
        The file's leading comment (its description), whether it is
        ``# @package _global_``, and the inline comment of every key by dotted path. A
        comment-only line indented under a key continues that key's comment. Items of
        the ``defaults`` list (``- env: highway_fast  # ...``) are keyed ``defaults.env``.
    """
    description: list[str] = []
    global_package = False
    comments: dict[str, str] = {}
    stack: list[tuple[int, str]] = []  # (indent, key) of the enclosing keys
    last_key: str | None = None
    last_indent = -1
    seen_key = False
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped:
            continue
        indent = len(line) - len(line.lstrip())
        if stripped.startswith("#"):
            body = stripped[1:].strip()
            if body.startswith("@package"):
                global_package = "_global_" in body
            elif not seen_key:
                description.append(body)
            elif last_key is not None and indent > last_indent and last_key in comments:
                comments[last_key] += " " + body
            continue
        seen_key = True
        match = _KEY_LINE.match(line)
        if match is None:
            last_key = None
            continue
        key_indent = indent + (len(match.group("dash")) if match.group("dash") else 0)
        while stack and stack[-1][0] >= key_indent:
            stack.pop()
        path = ".".join([k for _, k in stack] + [match.group("key")])
        comment = _split_comment(match.group("rest"))
        if comment:
            comments[path] = comment
        stack.append((key_indent, match.group("key")))
        last_key, last_indent = path, indent
    return " ".join(description), global_package, comments


def read_yaml(path: Path) -> YamlFile:
    """Reads one file of ``conf/``: values (PyYAML) and comments (line by line)."""
    text = path.read_text()
    description, global_package, comments = read_yaml_comments(text)
    data = yaml.safe_load(text) or {}
    return YamlFile(
        path=path,
        option=path.stem,
        description=description,
        global_package=global_package,
        defaults=list(data.pop("defaults", None) or []),
        values={k: v for k, v in data.items() if k not in HYDRA_KEYS},
        comments=comments,
    )


# --------------------------------------------------------------------------- schemas


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _enum_in(tp: Any) -> type[enum.Enum] | None:
    """The enum of a type (also inside ``X | None``), or None."""
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return tp
    for arg in typing.get_args(tp):
        found = _enum_in(arg)
        if found is not None:
            return found
    return None


def type_name(tp: Any) -> str:
    """A type hint as it is written in the schema: ``int``, ``float | None``, ``list[int]``."""
    if tp is type(None):
        return "None"
    if tp is Any:
        return "Any"
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_name(arg) for arg in typing.get_args(tp))
    if origin is not None:
        args = ", ".join(type_name(arg) for arg in typing.get_args(tp))
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    return getattr(tp, "__name__", str(tp))


def format_value(value: Any) -> str:
    """A value as it is written in the YAML files and on the command line."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {format_value(v)}" for k, v in value.items()) + "}"
    return str(value)


@dataclass
class SchemaKey:
    """One key of a schema (nested dataclasses give dotted keys)."""

    key: str
    type: str
    choices: list[str] | None
    default: str
    required: bool
    doc: str  # the enum's or nested dataclass's docstring summary, a fallback meaning
    nested: bool = False
    aliases: dict[str, str] = field(default_factory=dict)  # older spelling -> choice


def _summary(obj: Any) -> str:
    doc = inspect.getdoc(obj) or ""
    return doc.split("\n\n")[0].replace("\n", " ").strip()


def field_types(schema: type) -> dict[str, Any]:
    """Each field's type; a field typed ``Any`` names its schema in ``metadata["schema"]``."""
    hints = typing.get_type_hints(schema)
    return {f.name: f.metadata.get("schema", hints[f.name]) for f in dataclasses.fields(schema)}


def schema_keys(schema: type, prefix: str = "") -> list[SchemaKey]:
    """Every key of a dataclass schema, in field order, nested dataclasses expanded."""
    hints = field_types(schema)
    keys: list[SchemaKey] = []
    for f in dataclasses.fields(schema):
        tp = hints[f.name]
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = OMEGACONF_MISSING
        required = isinstance(default, str) and default == OMEGACONF_MISSING
        choices = None
        aliases: dict[str, str] = {}
        doc = ""
        enum_type = _enum_in(tp)
        if enum_type is not None:
            choices = [str(member.value) for member in enum_type]
            # Extra names of a member: spellings that still validate.
            aliases = {
                name: str(member.value)
                for name, member in enum_type.__members__.items()
                if name != member.name
            }
            doc = _summary(enum_type)
        name = prefix + f.name
        if _is_dataclass_type(tp):
            keys.append(SchemaKey(name, tp.__name__, None, "", required, _summary(tp), nested=True))
            if not required:
                keys.extend(schema_keys(tp, prefix=name + "."))
            continue
        keys.append(
            SchemaKey(
                key=name,
                type=type_name(tp),
                choices=choices,
                default=OMEGACONF_MISSING if required else format_value(default),
                required=required,
                doc=doc,
                aliases=aliases,
            )
        )
    return keys


def registered_schemas() -> tuple[dict[str, type], dict[str, dict[str, type]]]:
    """The schemas registered in Hydra's ConfigStore by ``register_configs``.

    Returns:
        The top-level schemas by name (``base_config``, ``base_evaluate``) and, per
        config group, the group's schemas by name (``base_grpo``, ``base_ppo``, ...). Only
        dataclasses of the schema module count (Hydra registers its own groups too).
    """
    from omegaconf import OmegaConf

    module = importlib.import_module(SCHEMA_MODULE)
    store = module.register_configs()

    def schema_of(path: str) -> type | None:
        node = store.load(path).node
        tp = OmegaConf.get_type(node)
        if _is_dataclass_type(tp) and tp.__module__.startswith(SCHEMA_PACKAGE + "."):
            return tp
        return None

    top: dict[str, type] = {}
    groups: dict[str, dict[str, type]] = {}
    for entry in store.list(""):
        if entry.endswith(".yaml"):
            tp = schema_of(entry)
            if tp is not None:
                top[entry.removesuffix(".yaml")] = tp
            continue
        for name in store.list(entry):
            tp = schema_of(f"{entry}/{name}")
            if tp is not None:
                groups.setdefault(entry, {})[name.removesuffix(".yaml")] = tp
    return top, groups


# --------------------------------------------------------------------------- flattening


def flatten(values: dict[str, Any], schema: type | None, prefix: str = "") -> dict[str, Any]:
    """YAML values by dotted key; a mapping is expanded where the schema has a dataclass."""
    hints = field_types(schema) if schema is not None else {}
    flat: dict[str, Any] = {}
    for key, value in values.items():
        sub = hints.get(key)
        if isinstance(value, dict) and _is_dataclass_type(sub):
            flat.update(flatten(value, sub, prefix=f"{prefix}{key}."))
        else:
            flat[prefix + key] = value
    return flat


def _default_names(defaults: list[Any]) -> list[str]:
    return [d for d in defaults if isinstance(d, str) and d != "_self_"]


def file_schema(
    file: YamlFile, schemas: dict[str, type], siblings: dict[str, YamlFile]
) -> str | None:
    """The name of the schema a group's file builds on (through its defaults list)."""
    seen: set[str] = set()
    current: YamlFile | None = file
    while current is not None and current.option not in seen:
        seen.add(current.option)
        names = _default_names(current.defaults)
        for name in names:
            if name in schemas:
                return name
        current = next((siblings[n] for n in names if n in siblings), None)
    if len(schemas) == 1:
        return next(iter(schemas))
    return None


# --------------------------------------------------------------------------- RST output


def _escape_chars(text: str) -> str:
    """Plain text for reStructuredText: inline markup characters escaped."""
    return re.sub(r"([\\*_|`\[\]<>])", r"\\\1", text)


def _escape(text: str) -> str:
    """A whole cell of plain text: escaped, and kept a paragraph (not a list)."""
    text = _escape_chars(text)
    if re.match(r"^([-+*#]|\d+[.)]|\(|[A-Za-z][.)]\s)", text):
        text = "\\" + text
    return text


_BEFORE_OK = set(" \t'\"([{<-/:")
_AFTER_OK = set(" \t'\")]}>-/:.,;!?")


def inline(text: str) -> str:
    """A YAML comment as reStructuredText: ```code``` spans become literals."""
    parts = text.split("`")
    if len(parts) % 2 == 0:  # unbalanced backticks: all plain text
        return _escape(text.strip())
    out = []
    for i, part in enumerate(parts):
        if i % 2 == 0:
            out.append(_escape(part.lstrip()) if i == 0 else _escape_chars(part))
            continue
        code = part.strip()
        if not code:
            continue
        before = parts[i - 1][-1:] if parts[i - 1].strip() else ""
        after = parts[i + 1][:1] if parts[i + 1] else ""
        out.append(
            ("" if not before or before in _BEFORE_OK else "\\ ")
            + literal(code)
            + ("" if not after or after in _AFTER_OK else "\\ ")
        )
    return "".join(out).strip()


def literal(text: object) -> str:
    """An inline literal."""
    text = str(text).strip()
    return f"``{text}``" if text else "\\-"


def _cell(text: str) -> str:
    return text.strip() or "\\-"


def list_table(
    header: list[str], rows: list[list[str]], css_class: str, widths: str = "auto"
) -> list[str]:
    """A ``list-table`` whose cells are already reStructuredText."""
    lines = [
        ".. list-table::",
        "   :header-rows: 1",
        f"   :class: {css_class}",
        f"   :widths: {widths}",
        "",
    ]
    for row in [header, *rows]:
        for i, cell in enumerate(row):
            bullet = "   * - " if i == 0 else "     - "
            lines.append(bullet + _cell(cell))
    lines.append("")
    return lines


def section(title: str, underline: str) -> list[str]:
    """A section title (the title is reStructuredText already)."""
    return [title, underline * max(len(title), 4), ""]


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
