#!/usr/bin/env python3
"""Regenerate the marked tables of docs/results.md and docs/benchmarks.md from JSON records.

A record is what ``bmi eval --json F`` and ``bmi bench NAME --json F`` write::

    {"command": str, "commit": str | null, "date": str, "machine": {...},
     "tables": [{"title": str, "columns": [str], "rows": [[...]], "notes": str}]}

Each record fills one section of a Markdown file, the text between ``<!-- generated: NAME -->`` and
``<!-- end generated: NAME -->``; everything outside those two lines is left byte for byte as it was.
The section is headed by one line naming the command, the commit, the date and the machine's load, then
holds one Markdown table per entry of ``tables`` (a ``###`` title above it, its notes below it).

Usage::

    python tools/docs_tables.py docs/benchmarks.md Inference=out/bench_infer.json [NAME=RECORD.json ...]

The script lives outside the installed package: the package never writes into the repository's docs.
It uses the standard library only.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import tempfile
from pathlib import Path

_REQUIRED = {"command": str, "date": str, "machine": dict, "tables": list}
_TABLE_REQUIRED = {"title": str, "columns": list, "rows": list}


class RecordError(ValueError):
    """A JSON record that does not follow the schema above; the message names the field and what it holds."""


def validate_record(record: object, source: str = "record") -> dict:
    """Return ``record`` if it follows the schema, else raise :class:`RecordError` naming the bad field."""
    if not isinstance(record, dict):
        raise RecordError(f"{source}: expected a JSON object, got {type(record).__name__}")
    for key, kind in _REQUIRED.items():
        if key not in record:
            raise RecordError(f"{source}: missing field '{key}' (needs command, commit, date, machine, tables)")
        if not isinstance(record[key], kind):
            raise RecordError(f"{source}: field '{key}' must be {kind.__name__}, got {type(record[key]).__name__}")
    if "commit" not in record:
        raise RecordError(f"{source}: missing field 'commit' (a string, or null when not in a git checkout)")
    if record["commit"] is not None and not isinstance(record["commit"], str):
        raise RecordError(f"{source}: field 'commit' must be a string or null, got {type(record['commit']).__name__}")
    if not record["tables"]:
        raise RecordError(f"{source}: field 'tables' is empty; a record holds at least one table")
    for i, table in enumerate(record["tables"]):
        where = f"{source}: tables[{i}]"
        if not isinstance(table, dict):
            raise RecordError(f"{where} must be an object, got {type(table).__name__}")
        for key, kind in _TABLE_REQUIRED.items():
            if key not in table:
                raise RecordError(f"{where}: missing field '{key}' (needs title, columns, rows)")
            if not isinstance(table[key], kind):
                raise RecordError(f"{where}: field '{key}' must be {kind.__name__}, got {type(table[key]).__name__}")
        if not table["columns"]:
            raise RecordError(f"{where}: field 'columns' is empty")
        if "notes" in table and not isinstance(table["notes"], str):
            raise RecordError(f"{where}: field 'notes' must be str, got {type(table['notes']).__name__}")
        for j, row in enumerate(table["rows"]):
            if not isinstance(row, list) or len(row) != len(table["columns"]):
                got = len(row) if isinstance(row, list) else type(row).__name__
                raise RecordError(f"{where}.rows[{j}] has {got} cells; columns has {len(table['columns'])}")
    return record


def _cell(value: object) -> str:
    """One table cell: floats to 4 significant digits (integers kept whole), '|' escaped, null as '–'."""
    if value is None:
        return "–"
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        if value.is_integer() and abs(value) < 1e6:
            return str(int(value))
        return f"{value:.4g}"
    return str(value).replace("|", "\\|").replace("\n", " ")


def _machine_load(machine: dict) -> str:
    """The machine as one phrase: its description fields, then its load average (the last is what wall times scale with)."""
    parts = [str(machine[k]) for k in ("name", "platform", "cpu") if machine.get(k)]
    if machine.get("cores"):
        parts.append(f"{machine['cores']} cores")
    if machine.get("python"):
        parts.append(f"Python {machine['python']}")
    load = machine.get("load_average", machine.get("load"))
    if isinstance(load, (list, tuple)):
        load = " / ".join(f"{float(x):.1f}" for x in load)
    parts.append(f"load {load}" if load is not None else "load not recorded")
    return ", ".join(parts)


def render_section(record: dict) -> str:
    """The Markdown that goes between a section's two markers (no markers, ends with a newline)."""
    commit = f"`{record['commit'][:12]}`" if record["commit"] else "not recorded"
    lines = [f"Command `{record['command']}` · commit {commit} · {record['date']} · "
             f"{_machine_load(record['machine'])}.", ""]
    for table in record["tables"]:
        lines += [f"### {table['title']}", ""]
        lines.append("| " + " | ".join(_cell(c) for c in table["columns"]) + " |")
        lines.append("|" + "---|" * len(table["columns"]))
        lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in table["rows"]]
        if table.get("notes", "").strip():
            lines += ["", table["notes"].strip()]
        lines.append("")
    return "\n".join(lines)


def replace_section(text: str, name: str, body: str, source: str = "document") -> str:
    """``text`` with the lines between the markers of ``name`` replaced by ``body``; an error if they are missing."""
    begin, end = f"<!-- generated: {name} -->", f"<!-- end generated: {name} -->"
    pattern = re.compile(rf"^{re.escape(begin)}[ \t]*\n.*?^{re.escape(end)}[ \t]*$", re.S | re.M)
    if not pattern.search(text):
        raise RecordError(f"{source}: no section '{name}' (expected the lines '{begin}' and '{end}')")
    return pattern.sub(lambda _: f"{begin}\n{body.rstrip()}\n{end}", text, count=1)


def load_record(path: Path) -> dict:
    """Read and check one JSON record file."""
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise RecordError(f"{path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    return validate_record(record, str(path))


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file beside ``path``, then rename it over ``path``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def update_document(doc: Path, sections: dict[str, Path]) -> None:
    """Fill each named section of ``doc`` from its record file; nothing is written unless every record is valid."""
    text = doc.read_text(encoding="utf-8")
    for name, record_path in sections.items():
        text = replace_section(text, name, render_section(load_record(record_path)), str(doc))
    _write_atomic(doc, text)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2 or any("=" not in a for a in argv[1:]):
        print("usage: python tools/docs_tables.py DOC.md NAME=RECORD.json [NAME=RECORD.json ...]", file=sys.stderr)
        return 2
    sections = dict(a.split("=", 1) for a in argv[1:])
    try:
        update_document(Path(argv[0]), {name: Path(p) for name, p in sections.items()})
    except (RecordError, OSError) as exc:
        print(f"docs_tables: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
