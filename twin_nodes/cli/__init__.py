"""The ``rotortwin`` command.

Every module in this package that defines ``register(subparsers)`` adds its own
subcommand(s); nothing here has to be edited to add one.  A subcommand's handler
is set with ``parser.set_defaults(func=handler)`` and returns an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from twin_nodes import __version__
from twin_nodes.base.errors import TwinError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except TwinError as exc:
        print(f"rotortwin: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("rotortwin: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
