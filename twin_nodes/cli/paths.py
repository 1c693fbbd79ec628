"""The paths a subcommand reads and writes, declared where its arguments are.

Every subcommand declares its path arguments through :func:`declare`::

    io = declare(p)
    io.input("flight", help="PX4 ULog")
    io.output("--json", help="write the result here")            # a file, staged
    io.output("--report", kind="dir", help="plots and index.html")

and :func:`run_guarded` (called by ``rotortwin``'s main for every command) checks each output
against the inputs before the command runs and commits the staged outputs when it returned
(:mod:`twin_nodes.base.outputs`).  A subcommand with an output gets ``--force`` (replace an
existing output).  ``tests/test_outputs.py`` walks the parser: a string argument that is neither a
declared path nor listed there as a non-path fails it, so a new command cannot skip the guard.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from dataclasses import dataclass, field
from typing import Any, Callable

from twin_nodes.base.errors import TwinError
from twin_nodes.base.outputs import Output, Staging, check, unstaged

__all__ = ["PathArgs", "declare", "run_guarded"]


@dataclass
class PathArgs:
    """The declared inputs and outputs of one subparser (stored in its defaults as ``_paths``)."""

    parser: argparse.ArgumentParser
    inputs: list[str] = field(default_factory=list)
    outputs: list[Output] = field(default_factory=list)
    also: dict[str, Callable[[str], list[str]]] = field(default_factory=dict)

    def input(self, *names: str, also: Callable[[str], list[str]] | None = None, **kw: Any) -> argparse.Action:
        """A path the command reads; ``also`` names more paths that belong to it (a bag's folder);
        ``group=`` adds it to an argument group of the parser (a mutually exclusive one)."""
        action = kw.pop("group", self.parser).add_argument(*names, **kw)
        self.inputs.append(action.dest)
        if also is not None:
            self.also[action.dest] = also
        return action

    def output(self, *names: str, kind: str = "file", staged: bool | None = None,
               path: Callable[[str], str] | None = None, fallback: Callable[[Any], str | None] | None = None,
               skip: Callable[[Any], bool] | None = None, **kw: Any) -> argparse.Action:
        """A path the command writes (see :class:`twin_nodes.base.outputs.Output`; ``fallback`` computes
        the path written when the option is not given)."""
        action = self.parser.add_argument(*names, **kw)
        option = next((n for n in names if n.startswith("--")), names[0])
        if not option.startswith("-"):
            option = option.upper()
        self.outputs.append(Output(action.dest, option, kind, kind != "update" if staged is None else staged,
                                   path, fallback, skip))
        if not any("--force" in a.option_strings for a in self.parser._actions):
            self.parser.add_argument("--force", action="store_true",
                                     help="replace outputs that exist already (an input is never replaced)")
        return action

    def input_values(self, args: argparse.Namespace) -> list[str]:
        vals: list[str] = []
        for dest in self.inputs:
            v = getattr(args, dest, None)
            given = [str(x) for x in v if x] if isinstance(v, (list, tuple)) else ([str(v)] if v else [])
            vals += given
            if dest in self.also:
                vals += [a for g in given for a in self.also[dest](g)]
        return vals


def declare(parser: argparse.ArgumentParser) -> PathArgs:
    """The path declarations of ``parser`` (made once, kept in its defaults)."""
    existing = parser.get_default("_paths")
    if isinstance(existing, PathArgs) and existing.parser is parser:
        return existing
    pa = PathArgs(parser)
    parser.set_defaults(_paths=pa)
    return pa


class _Terminated(KeyboardInterrupt):
    """SIGTERM/SIGHUP: handled like Ctrl-C, so staged outputs are removed on the way out."""


_OWNER = {"pid": 0, "at_fork": False}


def _raise_terminated(signum: int, frame: Any) -> None:
    if os.getpid() != _OWNER["pid"]:  # a child forked before _child_defaults could run: die as the signal says
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    raise _Terminated(signal.Signals(signum).name)


def _child_defaults() -> None:
    """In a process forked during a command (a multiprocessing pool worker, a background fit, Dask):
    SIGTERM and SIGHUP back to their default action, as before the command installed its handler.  A
    Python-level handler only runs when the worker's main thread returns to Python, and a pool
    worker blocked on its task queue while its pool is torn down must die at once."""
    for s in (signal.SIGTERM, signal.SIGHUP):
        try:
            if signal.getsignal(s) is _raise_terminated:
                signal.signal(s, signal.SIG_DFL)
        except (ValueError, OSError):  # not the main thread of the child: the handler above still applies
            pass


def run_guarded(func: Callable[[argparse.Namespace], Any], args: argparse.Namespace) -> int:
    """Check ``args``' outputs, run ``func`` on the staged paths, commit them when it returned 0 or 1
    (1: it ran to the end with a negative verdict, e.g. a regression); print each path written."""
    pa = getattr(args, "_paths", None)
    if not isinstance(pa, PathArgs) or not pa.outputs:
        return int(func(args) or 0)
    plan = check(pa.outputs, args, pa.input_values(args), force=bool(getattr(args, "force", False)))
    old = {}
    if _main_thread():
        _OWNER["pid"] = os.getpid()
        if not _OWNER["at_fork"]:
            os.register_at_fork(after_in_child=_child_defaults)
            _OWNER["at_fork"] = True
        for s in (signal.SIGTERM, signal.SIGHUP):
            old[s] = signal.signal(s, _raise_terminated)
    staging = Staging(plan)
    try:
        staging.begin()
        for pl in plan:
            setattr(args, pl.out.dest, str(pl.write))
        try:
            rc = int(func(args) or 0)
        except TwinError as exc:  # a message naming an output names the user's path, not the stage
            exc.args = (unstaged(str(exc)),)
            raise
        except OSError as exc:
            exc.filename = unstaged(exc.filename) if isinstance(exc.filename, str) else exc.filename
            raise
        if rc in (0, 1):
            try:
                done = staging.commit()
            except OSError as exc:
                raise TwinError(f"{exc.filename or exc.filename2 or '<output>'}: <output>: could not be moved into "
                                f"place ({exc.strerror or exc}); nothing else was changed") from None
            for p in done:
                print(f"wrote: {p}", file=sys.stderr)
        return rc
    finally:
        staging.abort()
        for s, h in old.items():
            signal.signal(s, h)


def _main_thread() -> bool:
    import threading
    return threading.current_thread() is threading.main_thread() and os.name == "posix"
