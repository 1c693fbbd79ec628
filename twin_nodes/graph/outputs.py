"""Output paths of the graph commands, checked before anything runs.

A run that takes minutes must not fail at its very end because ``--json`` points into a
folder that does not exist or cannot be written, and an output must never overwrite an
input (``compare F.ulg --json F.ulg``).  :func:`check_outputs` raises a one-line
:class:`TwinError` (exit 2, nothing written) for either.
"""

from __future__ import annotations

import os
from pathlib import Path

from twin_nodes.base.errors import TwinError

__all__ = ["check_output_file", "check_output_dir", "check_outputs"]


def _same(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def _writable_parent(path: Path, option: str) -> None:
    parent = path.resolve().parent
    if not parent.is_dir():
        raise TwinError(f"{path}: {option}: expected a path in an existing directory; {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise TwinError(f"{path}: {option}: expected a path in a writable directory; {parent} is not writable")


def check_output_file(path: str | os.PathLike[str], option: str, inputs: list[Path]) -> Path:
    """A file to (over)write: in an existing writable folder, not a folder, not an input."""
    p = Path(path)
    for i in inputs:
        if _same(p, i):
            raise TwinError(f"{p}: {option}: expected a new output file, not an input of the command ({i})")
    if p.is_dir():
        raise TwinError(f"{p}: {option}: expected a file, this is a directory")
    if p.exists() and not os.access(p, os.W_OK):
        raise TwinError(f"{p}: {option}: expected a writable file")
    _writable_parent(p, option)
    return p


def check_output_dir(path: str | os.PathLike[str], option: str, inputs: list[Path], new: bool = False) -> Path:
    """A folder to write into (``new``: one to create, that must not exist yet)."""
    p = Path(path)
    for i in inputs:
        if _same(p, i):
            raise TwinError(f"{p}: {option}: expected a new output directory, not an input of the command")
    if new and p.exists():
        raise TwinError(f"{p}: {option}: expected a new directory; it already exists")
    if p.exists():
        if not p.is_dir():
            raise TwinError(f"{p}: {option}: expected a directory, this is a file")
        if not os.access(p, os.W_OK | os.X_OK):
            raise TwinError(f"{p}: {option}: expected a writable directory")
        return p
    _writable_parent(p, option)
    return p


def check_outputs(inputs: list[str | os.PathLike[str] | None], *, files: dict[str, str | None] | None = None,
                  dirs: dict[str, str | None] | None = None, new_dirs: dict[str, str | None] | None = None) -> None:
    """Check every given output (``{option: path or None}``) against the inputs before a run."""
    ins = [Path(i) for i in inputs if i]
    for opt, path in (files or {}).items():
        if path:
            check_output_file(path, opt, ins)
    for opt, path in (dirs or {}).items():
        if path:
            check_output_dir(path, opt, ins)
    for opt, path in (new_dirs or {}).items():
        if path:
            check_output_dir(path, opt, ins, new=True)
