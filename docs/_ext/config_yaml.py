"""The YAML side of the config reference: each ``conf/`` file's keys, values and comments.

Part of the ``config-reference`` directive (``config_reference.py``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

# YAML keys that belong to Hydra, not to the schemas.
HYDRA_KEYS = ("defaults", "hydra")


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
