"""The `bmi` command line.

Every module in this package that defines ``register(subparsers)`` adds its
subcommands; ``main`` discovers them, so a new command group is one new file.
Handlers import their heavy dependencies (torch, jax, onnxruntime) inside the
handler so that ``bmi --help`` stays fast, and so that a command needs only the
extras it uses (``bmi_sdk.extras``): one that reaches for a missing extra stops
with one line naming it. Diagnostics (warnings, notes, errors) go through
``logging`` (``_logging``; ``-v`` / ``-q``), results to stdout.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from bmi_sdk.extras import MissingExtraError, needs_extra


def build_parser() -> argparse.ArgumentParser:
    from bmi_sdk import __version__

    parser = argparse.ArgumentParser(
        prog="bmi",
        description="bmi-sdk: monocentric RGBD camera — optics, simulation, device, calibration, inference.",
    )
    parser.add_argument("--version", action="version", version=f"bmi-sdk {__version__}")
    parser.add_argument("-v", "--verbose", dest="log_verbose", action="count", default=0,
                        help="more diagnostics on stderr (-v info, -vv debug)")
    parser.add_argument("-q", "--quiet", dest="log_quiet", action="count", default=0,
                        help="errors only on stderr (no warnings, notes or progress bars)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):  # __main__ and private helpers are not command groups
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    from ._logging import command_logger, configure

    parser = build_parser()
    args = parser.parse_args(argv)
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 2
    configure(args.log_verbose, args.log_quiet, args.command)
    log = command_logger(args.command)
    try:
        with needs_extra("this command"):
            return int(handler(args) or 0)
    except KeyboardInterrupt:
        log.error("cancelled")
        return 130
    except Exception as exc:
        if not isinstance(exc, _user_error_types()):
            raise  # a bug: keep the traceback
        log.error("%s", exc)
        return 2 if getattr(exc, "option", None) else 1  # a bad option value is a usage error, as argparse's


def _user_error_types() -> tuple[type, ...]:
    """Errors that carry a message for the user (bad input, a refused file, a camera that refused or failed,
    an extra that is not installed). One that names a command-line option (its ``option`` attribute:
    ``option_values.OptionError``, ``memory_budget.MemoryBudgetError`` from ``check_allocation``) exits 2.

    ``devices.errors.CameraError`` is looked up in ``sys.modules`` rather than
    imported: a command that raised one has loaded it, and ``bmi --help``
    stays free of the device stack.
    """
    # OSError covers FileNotFoundError, FileExistsError, TimeoutError
    types: list[type] = [ValueError, OSError, MissingExtraError]
    camera_errors = sys.modules.get("devices.errors")
    if camera_errors is not None:
        types.append(camera_errors.CameraError)
    return tuple(types)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
