"""reStructuredText pieces of the config reference: escaping, literals, list tables.

Part of the ``config-reference`` directive (``config_reference.py``).
"""

from __future__ import annotations

import re


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
