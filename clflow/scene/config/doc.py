"""The key tables of docs/scene_config.md, written from the schema.

Each table stands between ``<!-- keys: SECTION ... -->`` and ``<!-- end keys -->`` (a
section's path as :data:`~clflow.scene.config.schema.SECTIONS` names it, ``top`` for the
top level); the prose around the tables is written by hand. ``python -m
clflow.scene.config.doc`` writes the tables into the file; tests/scene/test_config_doc.py
holds the committed file equal to what this writes.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from clflow.scene.config.keys import Key
from clflow.scene.config.reader import interval
from clflow.scene.config.schema import SECTIONS, Section

DOC = Path(__file__).resolve().parents[3] / "docs" / "scene_config.md"
TABLE = re.compile(r"(<!-- keys: ([^>]*?) -->\n)(.*?)(<!-- end keys -->)", re.S)
TOP = "top"  # the top level's name in a marker


def shown(value) -> str:
    """A default as the tables write it: `32`, `0.1`, `[0, -9.81, 0]`, `+y`, `true`."""
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    if isinstance(value, (int, float)):
        return f"`{value:g}`" if isinstance(value, float) else f"`{value}`"
    if isinstance(value, tuple):
        return "`[" + ", ".join(f"{v:g}" for v in value) + "]`"
    if isinstance(value, str):
        return f"`{value}`" if value else '`""`'
    raise TypeError(f"no form for a default {value!r}")


def default_of(key: Key) -> str:
    if key.shown is not None:
        return key.shown
    if key.required:
        return "required"
    return "none" if key.default is None else shown(key.default)


def constraints_of(key: Key) -> str:
    """What ``key`` takes, from its kind and range, with its unit (a file key's meaning says
    which file)."""
    if key.kind == "integer":
        low = key.low or 0
        taken = f"integer {low}..{key.high}" if key.high is not None else f"integer >= {low}"
    elif key.kind == "number":
        taken = interval(key.low, key.high, key.strict_low) if (key.low, key.high) != (None, None) else "a number"
    elif key.kind == "vec3":
        taken = f"3 numbers within +-{key.high:g}" if key.high is not None else "3 numbers"
    elif key.kind == "choice":
        taken = "one of " + " ".join(f"`{c}`" for c in key.choices)
    elif key.kind == "flag":
        taken = "`true` or `false`"
    elif key.kind == "text":
        taken = "text"
    else:
        taken = ""
    if key.unit:
        taken = f"{taken}, {key.unit}" if taken else key.unit
    return taken


def _path(section: Section, key: Key) -> str:
    return f"{section.path}.{key.name}" if section.path else key.name


def rows(section: Section) -> list[str]:
    """The table rows of ``section``'s own keys (a sub-section's keys are its own rows)."""
    out = []
    for key in section.keys:
        if "." in key.name:
            continue
        meaning = "; ".join(part for part in (constraints_of(key), key.doc) if part)
        out.append(f"| `{_path(section, key)}` | {default_of(key)} | {meaning.replace('|', '&#124;')} |")
    return out


def table(paths: list[str]) -> str:
    lines = ["| key | default | constraints and meaning |", "|---|---|---|"]
    for path in paths:
        lines += rows(SECTIONS["" if path == TOP else path])
    return "\n".join(lines) + "\n"


def documented_sections(text: str) -> list[str]:
    """The sections the tables of ``text`` hold, in their order."""
    return [p for m in TABLE.finditer(text) for p in m.group(2).split()]


def written(text: str) -> str:
    """``text`` with each table between its markers written from the schema."""
    return TABLE.sub(lambda m: m.group(1) + table(m.group(2).split()) + m.group(4), text)


def main(argv: list[str]) -> int:
    """Write the tables into docs/scene_config.md (``--check``: only say whether they are current)."""
    text = DOC.read_text()
    new = written(text)
    if "--check" in argv:
        if new != text:
            print(f"{DOC}: the key tables are not current: run python -m clflow.scene.config.doc", file=sys.stderr)
            return 1
        return 0
    if new != text:
        DOC.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
