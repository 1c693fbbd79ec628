"""The ``rotortwin`` command.

Every module in this package that defines ``register(subparsers)`` adds its own
subcommand(s); nothing here has to be edited to add one.  A subcommand's handler
is set with ``parser.set_defaults(func=handler)`` and returns an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from twin_nodes import __version__
from twin_nodes.base.errors import TwinError


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose errors are one stderr line, exit code 2:
    ``rotortwin: error: --heldout: expected a number in (0, 1), got nan`` (a bad option value), or
    ``rotortwin: error: params from-ulog: <what argparse says>`` (no usage block).
    Subcommand parsers inherit the class (``add_subparsers`` uses the parent's type)."""

    def error(self, message: str):  # type: ignore[override]
        from twin_nodes.base.errors import one_line

        if message.startswith("argument "):
            message = message[len("argument "):]
        else:
            cmd = self.prog.removeprefix("rotortwin").strip()
            message = f"{cmd}: {message}" if cmd else message
        self.exit(2, f"rotortwin: error: {one_line(message)}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="rotortwin",
        description="Physics twin of a multirotor: simulate, replay, compare, discover missing physics.",
    )
    parser.add_argument("--version", action="version", version=f"rotortwin {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(sub)
    return parser


class _Once(logging.Filter):
    """Each warning once per command, however often the same log is loaded."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if msg in self.seen:
            return False
        self.seen.add(msg)
        return True


def _show_log_warnings() -> logging.Handler:
    """Data-loss warnings of the logs a command loads (``rotortwin.logs``) on stderr, one line each:
    ``rotortwin: warning: <file>: <what>``."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("rotortwin: warning: %(message)s"))
    handler.addFilter(_Once())
    logger = logging.getLogger("rotortwin")
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING)
    logger.propagate = False
    return handler


def main(argv: list[str] | None = None) -> int:
    handler = _show_log_warnings()
    try:
        return _main(argv)
    finally:
        logging.getLogger("rotortwin").removeHandler(handler)


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # a bad argument (one line already printed), --help, --version
        return exc.code if isinstance(exc.code, int) else 2
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    from twin_nodes.cli.paths import run_guarded

    try:
        return run_guarded(args.func, args)
    except TwinError as exc:
        print(f"rotortwin: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file the command reads or writes: one line, never a traceback
        from twin_nodes.base.errors import one_line

        where = exc.filename or exc.filename2 or "<file>"
        print(f"rotortwin: error: {one_line(where)}: <file>: {one_line(exc.strerror or exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        if str(exc) in ("SIGTERM", "SIGHUP"):
            print(f"rotortwin: stopped by {exc}", file=sys.stderr)
            return 143 if str(exc) == "SIGTERM" else 129
        print("rotortwin: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
