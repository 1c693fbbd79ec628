"""Small file helpers shared by every layer."""

from __future__ import annotations

import os
import stat
import tempfile
import warnings
from pathlib import Path

_CACHE_DIRS: dict[tuple[str, str], Path] = {}


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` via ``path.tmp`` and a rename, creating missing parent folders.

    A failed write never leaves a half-written ``path`` (nor the temporary file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text, encoding=encoding)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def cache_dir() -> Path:
    """A folder no one but this user can write (generated code, numba's cache, built nominals).

    ``$ROTORTWIN_CACHE``, else ``$XDG_CACHE_HOME/rotortwin`` (``~/.cache/rotortwin``); if that
    cannot be made or is not private, ``<tmp>/rotortwin-cache-<uid>``; if neither, a fresh
    ``mkdtemp`` folder for this process only."""
    base = os.environ.get("ROTORTWIN_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "rotortwin")
    key = (base, tempfile.gettempdir())
    if key not in _CACHE_DIRS:
        candidates = (Path(base), Path(key[1]) / f"rotortwin-cache-{os.getuid()}")
        path = next((p for p in candidates if private_dir(p)), None)
        if path is None:
            path = Path(tempfile.mkdtemp(prefix="rotortwin-cache-"))
            warnings.warn(f"rotortwin: no private cache folder; using {path} for this process only")
        _CACHE_DIRS[key] = path
    return _CACHE_DIRS[key]


def private_dir(path: Path) -> bool:
    """Make ``path`` (mode 0700) if missing; True if it is a folder (not a link) of this user,
    writable by this process and by no group or other user."""
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = path.lstat()
    except OSError:
        return False
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o022:
        warnings.warn(f"rotortwin: not using cache folder {path}: a link, another user's, or writable by "
                      f"others ({stat.filemode(st.st_mode)}); remove it or set ROTORTWIN_CACHE")
        return False
    return os.access(path, os.W_OK | os.X_OK)


__all__ = ["atomic_write_text", "cache_dir", "private_dir"]
