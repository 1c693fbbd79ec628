"""Generated flights kept on disk: ``<cache>/<name>.ulg`` beside ``<name>.meta.json`` holding the key of the
definition and code that made it (the flight is flown again when the key differs) and the flight's facts."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable


def keyed_flight(cache: str | Path, name: str, key: str, fly_to: Callable[[Path], dict], meta: dict | None = None,
                 remember_errors: bool = False) -> tuple[Path, dict]:
    """The ULog ``<cache>/<name>.ulg`` and its facts; flown first by ``fly_to(tmp_path) -> facts`` (written to
    a temporary name, renamed into place) when absent or made under another ``key``.  ``meta``: more fields for
    the meta file.  ``remember_errors``: a ``RuntimeError`` of ``fly_to`` (the flight could not be flown) is
    kept under the key and raised again without flying."""
    d = Path(cache)
    d.mkdir(parents=True, exist_ok=True)
    path, meta_path = d / f"{name}.ulg", d / f"{name}.meta.json"
    if path.is_file() or meta_path.is_file():
        m = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
        if m.get("key") == key:
            if m.get("error"):
                raise RuntimeError(m["error"])
            if path.is_file():
                return path, m["facts"]
    tmp = path.with_suffix(".tmp.ulg")
    try:
        facts = fly_to(tmp)
    except RuntimeError as e:
        if remember_errors:
            meta_path.write_text(json.dumps({"key": key, "error": str(e)}))
        raise
    tmp.replace(path)
    meta_path.write_text(json.dumps({"key": key, **(meta or {}), "facts": facts}, indent=1, default=float))
    return path, facts
