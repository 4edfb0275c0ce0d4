"""Diagnostics of the `bmi` command through ``logging``: one stderr handler, ``-v`` / ``-q`` set its level.

Results stay on stdout (``print``); progress bars draw on stderr, and warnings, notes and errors are log
records there, so a user can silence them (``-q``: errors only, no progress bars, ``bars_shown``) or ask for
more (``-v``: info, ``-vv``: debug, the library's own loggers included). Python warnings
(``FrameQualityWarning``, ``PsfCacheWarning``) become log records too, one line each instead of a warning with
its source line.

Dask (``--scheduler``) logs through its own handlers, in this process and in every worker process, at
INFO by default (some 40 lines for one run). Those loggers stay at WARNING unless ``-vv`` asks for
the library's own records; ``DASK_LOGGING__DISTRIBUTED`` set by the user wins.
"""

from __future__ import annotations

import logging
import os
import sys
import warnings

LOGGER_NAME = "bmi"
_command: str | None = None   # the running subcommand: Python warnings are logged under its name
_bars = True                  # whether the command draws progress bars (not under -q)
DASK_LEVEL_ENV = "DASK_LOGGING__DISTRIBUTED"
"""Dask's setting for its ``distributed`` loggers, read when it is imported, worker processes included."""
_user_dask_level = os.environ.get(DASK_LEVEL_ENV)


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
    global _command, _bars
    _command = command
    _bars = not quiet
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, _StderrHandler)]:
        root.removeHandler(handler)
    handler = _StderrHandler()
    handler.setFormatter(_Formatter())
    root.addHandler(handler)
    root.setLevel(verbosity_level(verbose, quiet))
    _quiet_dask(verbose, quiet)
    warnings.showwarning = _log_warning


def bars_shown(no_bar: bool = False) -> bool:
    """Whether the running command draws progress bars on stderr: not under ``-q`` (errors only), nor where the
    command's own options ask for none (``no_bar``: its ``--quiet``, or output meant for a program)."""
    return _bars and not no_bar


def dask_level(verbose: int, quiet: int) -> str:
    """The level of Dask's loggers: WARNING unless ``-vv`` (then INFO, Dask's own default), ERROR at ``-q``."""
    if quiet:
        return "error"
    return "info" if verbose >= 2 else "warning"


def _quiet_dask(verbose: int, quiet: int) -> None:
    """Set Dask's ``distributed`` loggers to ``dask_level``: through its setting for a Dask imported later and
    for worker processes (they inherit the environment), and on the loggers of a Dask already imported."""
    level = _user_dask_level or dask_level(verbose, quiet)
    os.environ[DASK_LEVEL_ENV] = level
    if "distributed" in sys.modules:
        logging.getLogger("distributed").setLevel(level.upper())


def _log_warning(message, category, filename, lineno, file=None, line=None) -> None:
    text = str(message) if issubclass(category, UserWarning) else f"{category.__name__}: {message}"
    command_logger(_command).warning(text)


def command_logger(command: str | None) -> logging.Logger:
    """The logger of one subcommand: its records read ``bmi COMMAND: level: text``."""
    return logging.getLogger(f"{LOGGER_NAME}.{command}" if command else LOGGER_NAME)
