"""The one YAML reader of user files: params files, derivation specs, mission plans, params maps.

``yaml.safe_load`` semantics, except that a mapping naming the same key twice is refused (PyYAML
keeps the last value silently, so a duplicated ``mass_kg:`` or ``km_m:`` would change the vehicle
without a word): :func:`read_yaml_file` raises the one-line ``<file>: <key>: duplicate key at line
N``.  YAML merge keys (``<<: *base``) may still be overridden by the mapping's own keys, as YAML
specifies.  libyaml's parser is used when it is installed (10x faster), unless the text could nest
deeper than it handles safely.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

from twin_nodes.base.errors import ParamsError

#: largest YAML file read [bytes] (params, derivation specs, mission plans)
MAX_FILE_BYTES = 1_000_000
_MERGE_TAG = "tag:yaml.org,2002:merge"


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping names ``key`` twice; ``line`` (1-based) is the second one."""

    def __init__(self, key: Any, line: int, first_line: int, mark: Any):
        self.key = key
        self.line = line
        self.first_line = first_line
        super().__init__(None, None, f"duplicate key {key!r} (first at line {first_line})", mark)


def _check_unique(loader: yaml.constructor.SafeConstructor, node: yaml.MappingNode) -> None:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == _MERGE_TAG:
            continue
        key = loader.construct_object(key_node, deep=False)
        try:
            first = seen.get(key)
        except TypeError:  # an unhashable key: SafeConstructor refuses it with its own message
            continue
        line = key_node.start_mark.line + 1
        if first is not None:
            raise DuplicateKeyError(key, line, first, key_node.start_mark)
        seen[key] = line


class UniqueKeySafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a duplicate key in any mapping (:class:`DuplicateKeyError`)."""

    def construct_mapping(self, node, deep=False):  # type: ignore[override]
        if isinstance(node, yaml.MappingNode):
            _check_unique(self, node)
        return super().construct_mapping(node, deep=deep)


_CLoader = getattr(yaml, "CSafeLoader", None)
if _CLoader is not None:
    class UniqueKeyCSafeLoader(_CLoader):  # type: ignore[valid-type, misc]
        """libyaml's parser with the same duplicate-key check."""

        def construct_mapping(self, node, deep=False):  # type: ignore[override]
            if isinstance(node, yaml.MappingNode):
                _check_unique(self, node)
            return super().construct_mapping(node, deep=deep)
else:  # pragma: no cover - PyYAML without libyaml
    UniqueKeyCSafeLoader = None  # type: ignore[assignment, misc]


def safe_load(text: str) -> Any:
    """``yaml.safe_load(text)`` that refuses duplicate keys (:class:`DuplicateKeyError`).  libyaml's
    parser unless the text could nest deeper than it handles safely (its C recursion crashes the
    process near 50 000 levels): nesting needs one of ``[{-?:`` per level, so more than 5000 of them
    use the Python parser, which raises RecursionError instead."""
    loader = UniqueKeyCSafeLoader
    if loader is None or sum(text.count(c) for c in "[{-?:") > 5000:
        loader = UniqueKeySafeLoader
    return yaml.load(text, Loader=loader)  # noqa: S506 - a safe loader


def read_yaml_file(path: str | Path, what: str = "YAML file") -> Any:
    """The YAML document in ``path`` (:func:`safe_load`), or a one-line ParamsError
    (``<file>: <file>|<key>|line N: ...``) when the path is missing, not a regular file, larger
    than MAX_FILE_BYTES, unreadable, not UTF-8, not YAML, or names a key twice in one mapping.
    Used for every YAML input (params files, derivation specs, mission plans, params maps)."""
    path = str(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            kind = "a directory" if stat.S_ISDIR(st.st_mode) else "not a regular file"
            raise ParamsError(path, "<file>", f"expected a {what}, got {kind}")
        if st.st_size > MAX_FILE_BYTES:
            raise ParamsError(path, "<file>", f"expected a {what} of at most {MAX_FILE_BYTES} bytes, "
                                              f"got {st.st_size}")
        with open(path, "rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise ParamsError(path, "<file>", "file not found") from None
    except OSError as exc:
        raise ParamsError(path, "<file>", f"expected a readable {what} ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ParamsError(path, "<file>", f"expected UTF-8 text, got byte 0x{raw[exc.start]:02x} at offset "
                                          f"{exc.start}") from None
    try:
        return safe_load(text)
    except DuplicateKeyError as exc:
        key = " ".join(str(exc.key).split())[:80]
        raise ParamsError(path, key, f"duplicate key at line {exc.line} (first at line {exc.first_line})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "<yaml>"
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())[:120]
        raise ParamsError(path, where, f"not valid YAML ({problem})") from None
    except RecursionError:
        raise ParamsError(path, "<yaml>", "not valid YAML (nested too deeply)") from None
