"""``--json PATH`` of ``bmi eval`` and every ``bmi bench TARGET``: a machine-readable record of a run's tables.

    {"command": "bmi bench psf --json out/psf.json", "commit": "<git rev or null>", "date": "2026-11-27",
     "machine": {"platform": "x86_64", "cores": 2, "python": "3.11.7", "load_average": [2.5, 1.9, 1.8]},
     "tables": [{"title": str, "columns": [str], "rows": [[...]], "notes": str}]}

The package never writes into a repository's docs: ``tools/docs_tables.py`` turns such records into the
generated sections of docs/results.md and docs/benchmarks.md. A benchmark prints markdown; ``markdown_tables``
reads its tables back (each titled by the heading above it, its notes the text between that heading and the
table), so the record holds exactly what was printed, numbers as numbers.
"""

from __future__ import annotations

import datetime
import functools
import os
import platform
import subprocess
import sys
from pathlib import Path

from ..io_atomic import write_json

EMPTY_CELLS = ("", "–", "—", "-")
"""Cells that hold no value (``None`` in a record)."""


def add_json_argument(p) -> None:
    """``--json PATH`` and ``--overwrite`` on parser ``p`` (the handler calls ``check_record_path`` first)."""
    p.add_argument("--json", default=None, metavar="PATH",
                   help="also write the tables as a JSON record (command, commit, date, machine, tables) to PATH, "
                        "for tools/docs_tables.py; a PATH that holds an earlier record is refused before the run "
                        "starts")
    p.add_argument("--overwrite", action="store_true", help="replace the earlier record at --json PATH")


def check_record_path(path, overwrite: bool) -> None:
    """Refuse, before a run's minutes of work, a ``--json`` PATH that is empty or a folder, whose folder cannot be made
    (it is made here), or that already holds a file (unless ``overwrite``): an earlier run's record is never replaced
    unasked. Also fixes the revision the record will name (``commit``) as the one the run starts from."""
    if path is None:
        return
    commit()  # the revision of the code about to run (memoised), not of whatever the checkout holds when it ends
    if not str(path).strip() or Path(path).is_dir():
        raise ValueError(f"--json {str(path)!r}: give the path of a file to write the record to, not a folder")
    folder = Path(path).absolute().parent
    try:  # made now, not when the record is written at the end of the run
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        why = "a file stands on its path" if isinstance(e, (FileExistsError, NotADirectoryError)) else e.strerror or e
        raise ValueError(f"--json {path}: its folder {folder} cannot be made ({why})") from None
    if not overwrite and Path(path).exists():
        raise FileExistsError(f"--json {path} holds an earlier run's record; pass --overwrite to replace it, or "
                              "choose another path")


def machine() -> dict:
    """The machine a run measured on: its platform, cores, Python and load averages (wall times scale with them)."""
    return {"platform": platform.machine(), "cores": os.cpu_count(), "python": platform.python_version(),
            "load_average": [round(x, 2) for x in os.getloadavg()]}


@functools.lru_cache(maxsize=1)
def commit() -> str | None:
    """The git revision of the checkout the package runs from, or None (an installed package, no git): read once per
    process, at the first call. ``check_record_path`` makes that call before a run's work starts, so a record names
    the code that ran even when the checkout moves on to another commit during a long run."""
    root = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else None


def cell(text: str):
    """A markdown cell as a record value: an int, a float, None (``EMPTY_CELLS``) or the text."""
    text = text.strip()
    if text in EMPTY_CELLS:
        return None
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _split_row(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def markdown_tables(text: str) -> list[dict]:
    """The tables of a markdown ``text`` as record tables: title (the nearest heading above, else the first line
    of the text above it, else "table N"), columns, rows and notes (the text between its title and the table;
    text after a table, up to the next heading or the end, joins that table's notes)."""
    tables: list[dict] = []
    heading, notes, block = None, [], []
    after_table = False  # the lines in ``notes`` follow a table under the current heading

    def join_trailing_notes() -> None:
        if after_table and notes:
            tables[-1]["notes"] = " ".join([tables[-1]["notes"], *notes]).strip()

    def close_table() -> None:
        nonlocal notes, block, after_table
        if not block:
            return
        rows = [_split_row(line) for line in block]
        body = [r for r in rows[2:]] if len(rows) > 1 and set("".join(rows[1])) <= set("-: ") else rows[1:]
        title = heading or (notes[0] if notes else f"table {len(tables) + 1}")
        tables.append({"title": title.rstrip(":"), "columns": rows[0], "rows": [[cell(c) for c in r] for r in body],
                       "notes": " ".join(n for n in notes if n != title).strip()})
        notes, block, after_table = [], [], True

    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("|"):
            block.append(stripped)
            continue
        close_table()
        if stripped.startswith("#"):
            join_trailing_notes()
            heading, notes, after_table = stripped.lstrip("#").strip(), [], False
        elif stripped:
            notes.append(stripped)
    close_table()
    join_trailing_notes()
    return tables


def write_record(path, tables: list[dict], argv: list[str] | None = None, overwrite: bool = False) -> Path:
    """Write the record of this run's ``tables`` to ``path`` (atomically); returns the path. Without ``overwrite``
    a file at ``path``, even one another run wrote meanwhile, is kept and ``FileExistsError`` raised."""
    argv = sys.argv[1:] if argv is None else argv
    record = {"command": " ".join(["bmi", *argv]), "commit": commit(), "date": datetime.date.today().isoformat(),
              "machine": machine(), "tables": tables}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        write_json(path, record, replace=overwrite)
    except FileExistsError:
        raise FileExistsError(f"--json {path} holds a record another run wrote meanwhile; this run's record was "
                              "not written (pass --overwrite to replace it)") from None
    return path
