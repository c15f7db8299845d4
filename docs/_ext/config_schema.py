"""The schema side of the config reference: every key's type, default and meaning.

The schemas are the dataclasses registered in Hydra's ConfigStore; part of the
``config-reference`` directive (``config_reference.py``).
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import inspect
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from config_yaml import YamlFile

SCHEMA_MODULE = "torchrl_grpo.training.config"
# The schemas are dataclasses of the training package (the algorithms' in their files).
SCHEMA_PACKAGE = "torchrl_grpo.training"
OMEGACONF_MISSING = "???"


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
