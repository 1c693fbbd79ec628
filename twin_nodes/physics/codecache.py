"""The per-user cache of compiled code for the generated numba modules (the dispatch stepper, discovery's kernels).

A generated module's file, and numba's on-disk cache of its functions beside it (``__pycache__``), live in
the **code cache** folder: ``$ROTORTWIN_CODE_CACHE``, else ``$XDG_CACHE_HOME/rotortwin/numba``
(``~/.cache/rotortwin/numba``), apart from the data cache (``$ROTORTWIN_CACHE``: built nominals), so that a
fresh data cache does not compile again what this user's machine compiled before.  ``make setup`` fills it
(``rotortwin fleet warm``), as pip byte-compiles ``.py`` files at install.

An entry can never be stale: a module's name is a digest of its generated source, of the kernels' sources
it calls, and of :func:`env_key` (Python, numpy, numba and llvmlite versions, the CPU numba compiles for,
numba's optimisation and bounds-check settings); numba's own index further checks its version, the
source file's bytes and the function's bytecode.  What runs is the generated text itself: its file is
used only when its bytes are that text (:func:`twin_nodes.physics.model._import_source`).

Never an error from the cache itself (:class:`_SafeCache`):

- concurrent processes: the module file and numba's index and data files are each written to a temporary
  name and renamed into place, so a reader sees a whole file or none;
- a read-only folder: what it holds is loaded, nothing is written (a missing module file falls back to the
  data cache folder, then to compiling in this process only);
- a full disk or any failed write: the compiled code is used in this process, the save is skipped (logged);
- a corrupt entry (an index or data file that does not load): its index is removed and the function is
  compiled again and saved anew.
"""

from __future__ import annotations

import hashlib
import logging
import os
import stat
import sys
import types
from pathlib import Path

from twin_nodes.base.io import private_dir

log = logging.getLogger("rotortwin.codecache")

#: folders whose generated modules use :class:`_EntryLocator` (absolute paths as strings)
_ENTRY_DIRS: set[str] = set()
_ENV_KEY: list[str] = []
_CODE_DIRS: dict[str, tuple[Path, bool] | None] = {}


def code_root() -> Path:
    """``$ROTORTWIN_CODE_CACHE``, else ``$XDG_CACHE_HOME/rotortwin/numba`` (``~/.cache/rotortwin/numba``)."""
    raw = os.environ.get("ROTORTWIN_CODE_CACHE")
    if raw:
        return Path(raw)
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(xdg) / "rotortwin" / "numba"


def code_dir() -> tuple[Path, bool] | None:
    """The code cache folder and whether this process may write it; None if it is unusable (a link,
    another user's, writable by others, or neither there nor creatable).  A folder of this user (or
    root's) that no one else may write is used read-only when this process cannot write it."""
    root = code_root()
    key = str(root)
    if key not in _CODE_DIRS:
        if private_dir(root):
            _CODE_DIRS[key] = (root, _writable(root))
        else:
            try:
                st = root.lstat()
                ok = stat.S_ISDIR(st.st_mode) and st.st_uid in (os.getuid(), 0) and not st.st_mode & 0o022
            except OSError:
                ok = False
            _CODE_DIRS[key] = (root, False) if ok and os.access(root, os.R_OK | os.X_OK) else None
    return _CODE_DIRS[key]


def _writable(folder: Path) -> bool:
    """True if a file can be made in ``folder`` (root ignores permission bits: ``os.access`` would say yes
    on a read-only mount)."""
    try:
        fd = os.open(folder / f".probe.{os.getpid()}", os.O_CREAT | os.O_WRONLY | os.O_EXCL, 0o600)
        os.close(fd)
        os.unlink(folder / f".probe.{os.getpid()}")
        return True
    except OSError:
        return False


def env_key() -> str:
    """What else compiled code depends on: Python, numpy, numba, llvmlite, the target CPU (numba's
    ``magic_tuple``: triple, CPU name, features) and numba's code-changing settings."""
    if not _ENV_KEY:
        import platform

        import llvmlite
        import numba
        import numpy
        from numba.core import config
        from numba.core.registry import cpu_target

        parts = [sys.implementation.name, platform.python_version(), getattr(sys, "abiflags", ""),
                 platform.machine(), numpy.__version__, numba.__version__, llvmlite.__version__,
                 repr(cpu_target.target_context.codegen().magic_tuple()),
                 repr((config.OPT, config.BOUNDSCHECK, config.FASTMATH if hasattr(config, "FASTMATH") else None))]
        _ENV_KEY.append(hashlib.sha256("\0".join(parts).encode()).hexdigest())
    return _ENV_KEY[0]


def lock_dir() -> Path:
    """Where the fleet's per-entry-point compile locks go: the code cache when writable (the processes that
    share it share its locks), else the data cache folder."""
    from twin_nodes.base.io import cache_dir

    d = code_dir()
    return d[0] if d is not None and d[1] else cache_dir()


# ------------------------------------------------------------------------ numba's cache, made safe
from numba.core.caching import NullCache

try:
    from numba.core.caching import CompileResultCacheImpl, FunctionCache, _CacheLocator
    try:
        from numba.core.caching import CacheImpl
    except ImportError:  # numba < 0.61 names it _CacheImpl
        from numba.core.caching import _CacheImpl as CacheImpl
except ImportError:  # pragma: no cover - another numba: its own cache, unguarded
    _SafeCache = None
else:
    class _EntryLocator(_CacheLocator):
        """numba's cache folder for a generated module: ``__pycache__`` beside its file, used even when the
        folder is read-only (loads work; a save fails and is skipped by :class:`_SafeCache`)."""

        def __init__(self, py_func, py_file):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno

        def get_cache_path(self):
            return os.path.join(os.path.dirname(self._py_file), "__pycache__")

        def get_source_stamp(self):
            try:
                with open(self._py_file, "rb") as f:
                    return hashlib.sha256(f.read()).digest()
            except OSError:  # no file: nothing on disk can match it
                return None

        def get_disambiguator(self):
            return str(self._lineno)

        @classmethod
        def from_function(cls, py_func, py_file):
            return cls(py_func, py_file) if os.path.dirname(os.path.abspath(py_file)) in _ENTRY_DIRS else None

    # before numba's own locators, for the generated modules' folders only (others: as numba decides)
    if _EntryLocator not in CacheImpl._locator_classes:
        CacheImpl._locator_classes.insert(0, _EntryLocator)

    class _SafeImpl(CompileResultCacheImpl):
        _locator_classes = [_EntryLocator]

    class _SafeCache(FunctionCache):
        """numba's function cache that never fails a call: a load that raises is a miss (the corrupt index
        removed, so the compiled code is saved anew), a save that raises is skipped."""

        _impl_class = _SafeImpl

        def load_overload(self, sig, target_context):
            try:
                return super().load_overload(sig, target_context)
            except Exception as exc:  # noqa: BLE001 - any unreadable entry: compile instead
                log.warning("numba cache entry for %s unreadable (%s: %s): compiling it again", self._name,
                            type(exc).__name__, exc)
                try:
                    os.unlink(self._cache_file._index_path)
                except OSError:
                    pass
                return None

        def save_overload(self, sig, data):
            try:
                super().save_overload(sig, data)
            except Exception as exc:  # noqa: BLE001 - a read-only or full folder: the code runs, unsaved
                log.info("numba cache: not saved for %s (%s: %s)", self._name, type(exc).__name__, exc)


def register(folder: Path) -> None:
    """Let numba cache the functions of modules whose file is in ``folder`` through :class:`_EntryLocator`."""
    _ENTRY_DIRS.add(os.path.abspath(str(folder)))


def adopt(mod: types.ModuleType, on_disk: bool) -> None:
    """Give each numba function defined in ``mod`` the safe cache (``on_disk``), or no disk cache at all
    (its file could not be written: compiled in this process only)."""
    from numba.core.dispatcher import Dispatcher

    for v in vars(mod).values():
        if isinstance(v, Dispatcher) and v.py_func.__module__ == mod.__name__ and not isinstance(v._cache, NullCache):
            if not on_disk:
                v._cache = NullCache()
            elif _SafeCache is not None:  # else numba's own cache, as it made it
                v._cache = _SafeCache(v.py_func)


__all__ = ["adopt", "code_dir", "code_root", "env_key", "lock_dir", "register"]
