"""Every path a command writes: checked before any work starts, written where a failure leaves nothing.

One guard for every command (the CLI layer calls it; no command checks its own outputs):

* :func:`check` refuses, before anything runs, an output that is an input, lies inside an input
  folder, holds an input (a folder output), is a symbolic or hard link to an input, is named twice,
  already exists (unless ``force``), or cannot be written (a missing folder is fine when its nearest
  existing ancestor is a writable folder).
* :class:`Staging` gives the command a private path for every *staged* output, inside a hidden
  folder ``.rotortwin-stage-<pid>-*`` next to where the output goes (same file system), and
  :meth:`Staging.commit` renames them into place only when the whole command returned.  An error,
  Ctrl-C or SIGTERM before that removes the stage: nothing partial is left, and nothing that was
  there before is touched.  A stage left by a killed process (``kill -9``) is removed by the next
  run that stages beside it.
* Outputs that are not staged: recordings that must survive a kill (``live --mcap``, the recorder
  node), node outputs written by another process, and folders that are updated on purpose
  (``fleet --catalog``, resumable).  They are checked all the same.

An output is described by :class:`Output`; its ``kind`` is ``file`` (one file), ``dir`` (a folder the
command fills; an existing one must be empty unless ``force``; with ``force`` its entries of the same
name are replaced and the rest kept), ``update`` (a folder kept across runs: may exist, never staged)
or ``bag`` (a recording: a path ending in ``.mcap`` is checked as a ``file``, any other as a ``dir``).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from twin_nodes.base.errors import TwinError, one_line

__all__ = ["Output", "Planned", "Staging", "check", "shown", "unstaged", "STAGE_PREFIX"]

STAGE_PREFIX = ".rotortwin-stage-"
KINDS = ("file", "dir", "update", "bag")

#: staged path -> final path of the outputs of the command running in this process (for what it prints)
_SHOWN: dict[str, str] = {}


@dataclass(frozen=True)
class Output:
    """One output option of a command.

    ``dest``: the argparse destination; ``option``: what the user typed (``--json``, ``OUT``);
    ``kind``: ``file`` | ``dir`` | ``update`` | ``bag`` (``file`` for a value ending in ``.mcap``,
    else ``dir``); ``staged``: written via the stage (default for ``file``, ``dir`` and ``bag``);
    ``path``: maps the given value to the path really written; ``default``: the path written when the option is not given (computed
    from the other arguments); ``skip``: the option is not an output for these arguments."""

    dest: str
    option: str
    kind: str = "file"
    staged: bool = True
    path: Callable[[str], str] | None = None
    default: Callable[[Any], str | None] | None = None
    skip: Callable[[Any], bool] | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Output {self.option}: kind {self.kind!r} not in {KINDS}")
        if self.kind == "update" and self.staged:
            object.__setattr__(self, "staged", False)


@dataclass
class Planned:
    """An output as it will be written: the user's ``value``, the ``final`` path, the ``write`` path
    given to the command (the staged one, or ``final``), and whether it is replaced (``force``)."""

    out: Output
    value: str
    final: Path
    write: Path
    replaces: bool = False


def _abs(p: Path) -> Path:
    """Absolute, normalised, symbolic links resolved where they exist."""
    return Path(os.path.realpath(os.path.abspath(p)))


def _inside(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def _nearest_existing(p: Path) -> Path:
    q = p
    while not os.path.lexists(q):
        if q.parent == q:
            break
        q = q.parent
    return q


def _err(path: str | Path, option: str, expected: str) -> TwinError:
    return TwinError(f"{one_line(path)}: {option}: {expected}")


def _against_inputs(p: Path, value: str, option: str, kind: str, inputs: list[Path]) -> None:
    """Refuse ``p`` if it is, contains, lies in, or links to an input."""
    real = _abs(p)
    for i in inputs:
        ri = _abs(i)
        same = real == ri
        if not same and os.path.exists(p) and os.path.exists(i):
            try:
                same = os.path.samefile(p, i)  # a hard link, or a link through another name
            except OSError:
                same = False
        if same:
            raise _err(value, option, f"expected a new output, not an input of the command ({i})")
        if os.path.isdir(ri) and _inside(real, ri):
            raise _err(value, option, f"expected an output outside the input folder {i}")
        if kind != "file" and _inside(ri, real):
            raise _err(value, option, f"expected an output folder that does not hold an input ({i})")


def _writable_place(p: Path, value: str, option: str) -> None:
    anc = _nearest_existing(p.parent if p.parent != p else p)
    if not anc.is_dir():
        raise _err(value, option, f"expected a path in a folder; {anc} is a file")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise _err(value, option, f"expected a path in a writable folder; {anc} is not writable")


def check(outputs: Iterable[Output], args: Any, inputs: Iterable[str | os.PathLike[str] | None],
          force: bool = False) -> list[Planned]:
    """Every output of ``args`` checked against ``inputs``; a one-line :class:`TwinError` for the first
    that fails.  Returns the plan (write paths still the final ones: :class:`Staging` assigns stages)."""
    ins = [Path(os.path.expanduser(str(i))) for i in inputs if i not in (None, "")]
    plan: list[Planned] = []
    for out in outputs:
        if out.skip is not None and out.skip(args):
            continue
        value = getattr(args, out.dest, None)
        if value in (None, "") and out.default is not None:
            value = out.default(args)
        if value in (None, ""):
            continue
        value = str(value)
        p = Path(os.path.expanduser(out.path(value) if out.path else value))
        kind = out.kind if out.kind != "bag" else ("file" if p.suffix == ".mcap" else "dir")
        _against_inputs(p, value, out.option, kind, ins)
        for other in plan:
            a, b = _abs(p), _abs(other.final)
            if a == b:
                raise _err(value, out.option, f"expected another path than {other.out.option}'s")
        exists = os.path.lexists(p)
        replaces = False
        if kind == "file":
            if exists and os.path.isdir(p):
                raise _err(value, out.option, "expected a file path, this is a folder")
            if exists and not force:
                raise _err(value, out.option, "expected a new file; it exists (pass --force to replace it)")
            if exists and os.path.exists(p) and not os.access(p, os.W_OK):
                raise _err(value, out.option, "expected a writable file")
            replaces = exists
        else:
            if exists and not os.path.isdir(p):
                raise _err(value, out.option, "expected a folder, this is a file")
            if exists and not os.access(p, os.W_OK | os.X_OK):
                raise _err(value, out.option, "expected a writable folder")
            if exists and kind == "dir" and any(os.scandir(p)) and not force:
                n = sum(1 for _ in os.scandir(p))
                raise _err(value, out.option, f"expected a new or empty folder; it holds {n} entries "
                                              f"(pass --force to write into it, replacing entries of the same name)")
            replaces = exists
        _writable_place(p, value, out.option)
        plan.append(Planned(out, value, p, p, replaces))
    return plan


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _clean_stale(folder: Path) -> None:
    """Remove stages beside ``folder`` left by processes that no longer run (``kill -9``)."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for e in entries:
        if not e.name.startswith(STAGE_PREFIX):
            continue
        try:
            pid = int(e.name[len(STAGE_PREFIX):].split("-", 1)[0])
        except ValueError:
            continue
        if pid != os.getpid() and not _pid_alive(pid):
            shutil.rmtree(e.path, ignore_errors=True)


@dataclass
class Staging:
    """The stage of one command's outputs: :meth:`begin` assigns the write paths, :meth:`commit`
    renames them into place, :meth:`abort` removes everything staged (idempotent)."""

    plan: list[Planned]
    stages: list[Path] = field(default_factory=list)
    committed: list[Path] = field(default_factory=list)

    def begin(self) -> "Staging":
        for pl in self.plan:
            if not pl.out.staged:
                continue
            home = _nearest_existing(pl.final.parent)
            _clean_stale(home)
            stage = Path(tempfile.mkdtemp(prefix=f"{STAGE_PREFIX}{os.getpid()}-", dir=home))
            self.stages.append(stage)
            pl.write = stage / pl.final.name
            _SHOWN[str(pl.write)] = str(pl.final)
        return self

    def commit(self) -> list[Path]:
        """Move every staged output into place (folders first, so a file output inside a folder
        output lands in it); returns the final paths that now exist."""
        for pl in sorted(self.plan, key=lambda q: q.out.kind == "file"):
            if not pl.out.staged:
                if os.path.lexists(pl.final):
                    self.committed.append(pl.final)
                continue
            if not os.path.lexists(pl.write):
                continue  # the command chose not to write it (e.g. nothing accepted)
            pl.final.parent.mkdir(parents=True, exist_ok=True)
            if pl.write.is_dir() and not pl.write.is_symlink() and pl.final.is_dir():
                for e in os.scandir(pl.write):  # --force into an existing folder: same names replaced
                    dst = pl.final / e.name
                    if os.path.isdir(dst) and not os.path.islink(dst):
                        shutil.rmtree(dst)
                    os.replace(e.path, dst)
            else:
                os.replace(pl.write, pl.final)
            self.committed.append(pl.final)
        self.abort()
        return self.committed

    def abort(self) -> None:
        for s in self.stages:
            shutil.rmtree(s, ignore_errors=True)
        self.stages.clear()
        for pl in self.plan:
            _SHOWN.pop(str(pl.write), None)


def unstaged(text: str) -> str:
    """``text`` (an error message) with every staged path of this process replaced by the user's."""
    for staged, final in _SHOWN.items():
        text = text.replace(staged, final)
    return text


def shown(path: str | os.PathLike[str] | None) -> str:
    """The path a user asked for, for a path the command was given (a staged one, or below it)."""
    s = str(path)
    for staged, final in _SHOWN.items():
        if s == staged:
            return final
        if s.startswith(staged + os.sep):
            return final + s[len(staged):]
    return s
