"""docs/configuration.md documents every configuration section and key the code reads, and nothing else.

The settings sections are dataclasses (``uacell.config.section_types()``): each field must have a row
in the table under the heading ``## `[section]` `` with a matching type and, where the default is a
plain value, that default. The cell's tables are read by ``uacell.core.cell_file.Table``: the keys their
parsers ask for (recorded while a probe cell is read, with the getter that read each) must be the rows
under ``## `[[robots]]` ``, ``### `[[robots.controllers]]` `` and so on, their types matching the getter.

Adding a key or a section? This test names what the page lacks; add a row
``| `key` | type | default | meaning |`` to the section's table (or a heading with a table).
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from uacell.catalog import companions
from uacell.config import section_types
from uacell.core.cell_file import IDENTIFICATION, Table, parse_cell

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "configuration.md"
USER_DOCS = ["README.md"] + [
    f"docs/{d}.md"
    for d in ("configuration", "operations", "web", "robotics", "programs", "packml", "security", "equipment")
]

# Words the Type column uses for each Python type of a settings field.
TYPE_WORDS = {
    "bool": ("boolean",),
    "int": ("integer",),
    "float": ("number",),
    "str": ("string", "path", '"'),  # a path given as text, or a choice of quoted values
    "Path": ("path",),
    "dict": ("table",),
    "list": ("list",),
}

# A cell that makes every parser ask for every key (names are dropped from the table paths).
PROBE = """
[[robots]]
name = "R"
  [[robots.controllers]]
  name = "C"
    [[robots.controllers.task_controls]]
    name = "T"
  [[robots.motion_devices]]
  name = "M"
    [[robots.motion_devices.axes]]
    name = "J"
[[packml_units]]
name = "U"
[[machines]]
name = "U"
"""
PROBE_NAMES = {"R", "C", "T", "M", "J", "U"}
# Tables whose keys are not fixed (documented in prose): free settings, per-state times, DI identification
# (checked against IDENTIFICATION below).
FREE = {"identification", "acting_times"}


def documented_tables() -> dict[str, dict[str, list[str]]]:
    """{table: {key: [type, default, meaning]}} of every heading that names a table in backquotes."""
    tables: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        heading = re.match(r"#+ `\[{0,2}([\w.]+)\]{0,2}`", line)
        if heading:
            current = tables.setdefault(heading.group(1), {})
        elif line.startswith("#"):
            current = None
        elif current is not None:
            row = re.match(r"\| `(\w+)` \|(.*)\|$", line)
            if row:
                current[row.group(1)] = [cell.strip() for cell in row.group(2).split(" | ")]
    return tables


def toml_literal(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, dict):
        return "{}"
    return repr(value)


def row_hint(section: str, key: str) -> str:
    return f"add `| `{key}` | type | default | meaning |` to the table under the heading '## `[{section}]`'"


def test_every_settings_section_and_key_is_documented_with_its_type_and_default():
    documented = documented_tables()
    problems = []
    for section, cls in section_types().items():
        rows = documented.get(section)
        if rows is None:
            problems.append(f"no heading '## `[{section}]`' with a table of its keys in docs/configuration.md")
            continue
        hints = {f.name: f.type for f in dataclasses.fields(cls)}
        defaults = vars(cls())
        for key, value in defaults.items():
            if key not in rows:
                problems.append(f"[{section}] {key} is not documented: {row_hint(section, key)}")
                continue
            kind, default_text = rows[key][0], rows[key][1]
            words = TYPE_WORDS[re.split(r"[ |\[]", str(hints[key]))[0]]  # "bool | None" -> bool
            if not any(word in kind for word in words):
                problems.append(f"[{section}] {key}: the type {kind!r} does not say {' or '.join(words)}")
            field = next(f for f in dataclasses.fields(cls) if f.name == key)
            literal = field.default is not dataclasses.MISSING or value == {}
            if literal and value is not None and f"`{toml_literal(value)}`" not in default_text:
                problems.append(f"[{section}] {key}: the default {default_text!r} does not say `{toml_literal(value)}`")
        for key in rows.keys() - defaults.keys():
            problems.append(f"[{section}] {key} is documented but the code has no such key")
    assert not problems, "docs/configuration.md and the code disagree:\n" + "\n".join(problems)


# What the Type column says for each Table getter (keys read raw, e.g. axes, are not checked).
GETTER_WORDS = {
    "string": ("string", '"'),
    "choice": ('"', "name"),
    "name": ("name",),
    "number": ("number",),
    "integer": ("integer",),
    "tables": ("array of tables",),
    "table": ("table",),
    "free_table": ("table",),
}


def asked_keys(monkeypatch: pytest.MonkeyPatch) -> dict[str, dict[str, str]]:
    """{table path without names: {key: the getter that first asked for it}} while the probe is read."""
    kinds: dict[int, dict[str, str]] = {}
    asked: dict[str, dict[str, str]] = {}
    finish = Table.finish

    def recording(self: Table) -> None:
        path = ".".join(p for p in re.sub(r"\[\d+\]", "", self.where).split(".") if p not in PROBE_NAMES)
        seen = asked.setdefault(path, {})
        for key in self.seen:
            seen.setdefault(key, kinds.get(id(self), {}).get(key, "raw"))
        finish(self)

    def getter(name: str, kind: str) -> Any:
        original = getattr(Table, name)

        def record(self: Table, key: str = "name", *args: Any, **kwargs: Any) -> Any:
            kinds.setdefault(id(self), {}).setdefault(key, kind)
            return original(self, key, *args, **kwargs)

        return record

    monkeypatch.setattr(Table, "finish", recording)
    for name in GETTER_WORDS:
        monkeypatch.setattr(Table, name, getter(name, name))
    monkeypatch.setattr(Table, "optional_number", getter("optional_number", "number"))
    parsers = {c.cell_section: c.cell_parser for c in companions() if c.cell_section and c.cell_parser}
    data: dict[str, Any] = tomllib.loads(PROBE)
    parse_cell(data, "probe.toml", parsers)
    assert set(parsers) <= set(data), "the probe cell must have an entry for every cell section"
    return asked


def test_every_cell_table_and_key_is_documented_with_its_type(monkeypatch):
    documented = documented_tables()
    problems = []
    asked = asked_keys(monkeypatch)
    assert {"robots", "robots.controllers", "robots.motion_devices.axes", "packml_units"} <= asked.keys()
    for table, keys in sorted(asked.items()):
        if table.rsplit(".", 1)[-1] in FREE:
            continue
        rows = documented.get(table)
        if rows is None:
            problems.append(f"no heading with `[[{table}]]` and a table of its keys in docs/configuration.md")
            continue
        for key, getter in sorted(keys.items()):
            if key not in rows:
                problems.append(f"[[{table}]] {key} is not documented: add `| `{key}` | type | default | meaning |`")
            elif getter in GETTER_WORDS and not any(w in rows[key][0] for w in GETTER_WORDS[getter]):
                problems.append(f"[[{table}]] {key}: the type {rows[key][0]!r} does not say {GETTER_WORDS[getter]}")
        problems += [f"[[{table}]] {key} is documented but not read" for key in sorted(rows.keys() - keys.keys())]
    assert not problems, "docs/configuration.md and the code disagree:\n" + "\n".join(problems)


def test_the_identification_table_lists_every_di_property():
    rows = documented_tables()["identification"]
    assert {key: cells[0].strip("`") for key, cells in rows.items()} == IDENTIFICATION


def test_no_user_document_sends_readers_to_the_source_for_a_key():
    for doc in USER_DOCS:
        text = (ROOT / doc).read_text(encoding="utf-8")
        assert not re.search(r"src/uacell/\S*config\S*\.py", text), f"{doc} sends readers to the source for keys"
