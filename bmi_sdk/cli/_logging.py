"""Diagnostics of the `bmi` command through ``logging``: one stderr handler, ``-v`` / ``-q`` set its level.

Results and progress stay on stdout (``print``); warnings, notes and errors are log records, so a user
can silence them (``-q``: errors only) or ask for more (``-v``: info, ``-vv``: debug, the library's own
loggers included). Python warnings (``FrameQualityWarning``, ``PsfCacheWarning``) become log records
too, one line each instead of a warning with its source line.
"""

from __future__ import annotations

import logging
import sys
import warnings

LOGGER_NAME = "bmi"
_command: str | None = None   # the running subcommand: Python warnings are logged under its name


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record (a test's capture, a redirected shell)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        pass


class _Formatter(logging.Formatter):
    """``bmi infer: warning: text`` for the command's own loggers, ``module: level: text`` for the library's."""

    def format(self, record: logging.LogRecord) -> str:
        where = record.name.replace(".", " ", 1) if record.name.startswith(LOGGER_NAME + ".") else record.name
        return f"{where}: {record.levelname.lower()}: {record.getMessage()}"


def verbosity_level(verbose: int, quiet: int) -> int:
    """The stderr level: WARNING by default, one step down per ``-v``, ERROR at any ``-q`` (errors always show)."""
    if quiet:
        return logging.ERROR
    return max(logging.DEBUG, logging.WARNING - 10 * verbose)


def configure(verbose: int = 0, quiet: int = 0, command: str | None = None) -> None:
    """(Re)install the one stderr handler at the level ``-v``/``-q`` ask for, and route Python warnings to
    ``command``'s logger."""
    global _command
    _command = command
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, _StderrHandler)]:
        root.removeHandler(handler)
    handler = _StderrHandler()
    handler.setFormatter(_Formatter())
    root.addHandler(handler)
    root.setLevel(verbosity_level(verbose, quiet))
    warnings.showwarning = _log_warning


def _log_warning(message, category, filename, lineno, file=None, line=None) -> None:
    text = str(message) if issubclass(category, UserWarning) else f"{category.__name__}: {message}"
    command_logger(_command).warning(text)


def command_logger(command: str | None) -> logging.Logger:
    """The logger of one subcommand: its records read ``bmi COMMAND: level: text``."""
    return logging.getLogger(f"{LOGGER_NAME}.{command}" if command else LOGGER_NAME)
