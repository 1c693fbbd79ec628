"""Public PX4 logs fetched into a private cache, never into the repository.

``TESTLOGS`` names each log by its repository, commit, path and git blob id; the file is kept as
``<cache>/<blob>.ulg`` (``$ROTORTWIN_TESTLOGS``, else ``~/.cache/rotortwin/testlogs``) and fetched
again with ``python tools/fetch_testlogs.py``, which checks the blob id.  A test that needs one calls
:func:`need_testlog`, which skips with a one-line reason when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

#: name -> (repository, commit, path in it, git blob id)
TESTLOGS: dict[str, tuple[str, str, str, str]] = {
    # PX4 master 2016 (fd48332), AUAV X2.1 quad: vehicle_attitude rates, PWM_MIN/MAX, never armed
    "pyulog_sample": ("PX4/pyulog", "dd44f431deb1f9b2075b7d513d41073b459b1109", "test/sample.ulg",
                      "d9c71bbc53e3b12c28e15440c68b358d3a6a0722"),
    # PX4 1.6-dev (f54a6c2), Pixracer-class FMU v4pro quad 4001: same layout, armed but landed throughout
    "pyulog_sample_appended_multiple": (
        "PX4/pyulog", "dd44f431deb1f9b2075b7d513d41073b459b1109", "test/sample_appended_multiple.ulg",
        "760a80ffad47ed27f5a2ffc6d006bc4fbb9be0ea"),
}


def cache_dir() -> Path:
    env = os.environ.get("ROTORTWIN_TESTLOGS", "").strip()
    return Path(env) if env else Path.home() / ".cache" / "rotortwin" / "testlogs"


def testlog_path(name: str) -> Path:
    return cache_dir() / f"{TESTLOGS[name][3]}.ulg"


def need_testlog(name: str) -> Path:
    """The cached log ``name``, or a skip naming what is missing and how to fetch it."""
    p = testlog_path(name)
    if not p.is_file():
        repo, _, path, blob = TESTLOGS[name]
        pytest.skip(f"{name} ({repo}:{path}, blob {blob[:10]}) not in {cache_dir()}: "
                    "python tools/fetch_testlogs.py")
    return p
