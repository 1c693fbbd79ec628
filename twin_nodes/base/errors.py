"""All project exceptions live here (one home)."""

from __future__ import annotations


class TwinError(Exception):
    """Base class for every error rotortwin raises on bad input."""


def one_line(text: object) -> str:
    """``str(text)`` with line breaks and other control characters escaped (``\\n``), so
    a message built from file content (a YAML key, a ULog topic name) stays one line."""
    s = str(text)
    if s.isprintable():
        return s
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in s)


class ParamsError(TwinError, ValueError):
    """A parameter file is missing a key, has a wrong type or an unphysical value.

    The message always reads ``<file>: <key>: <what was expected>``, on one line.
    """

    def __init__(self, path: str, key: str, expected: str):
        self.path = str(path)
        self.key = key
        self.expected = expected
        super().__init__(f"{one_line(self.path)}: {one_line(key)}: {one_line(expected)}")


class LogError(TwinError):
    """A flight log (ULog, MCAP, CSV) cannot be read or lacks what is needed.

    The message reads ``<file>: <topic/field>: <what was expected>``.
    """

    def __init__(self, path: str, field: str, expected: str):
        self.path = str(path)
        self.field = field
        self.expected = expected
        super().__init__(f"{one_line(self.path)}: {one_line(field)}: {one_line(expected)}")
