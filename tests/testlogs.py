"""Public PX4 logs fetched into a private cache, never into the repository.

``TESTLOGS`` names each log by its repository, commit, path and git blob id; the file is kept as
``<cache>/<blob>.ulg`` (``$ROTORTWIN_TESTLOGS``, else ``~/.cache/rotortwin/testlogs``; else the corpus
cache's tuning half, where those logs carry the same name) and fetched again with
``python tools/fetch_testlogs.py``, which checks the blob id.  A test that needs one calls
:func:`need_testlog`, which skips with a one-line reason when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

#: name -> (repository, commit, path in it, git blob id).  Real PX4 logs of the older topic sets; the
#: ones also in the project corpus (docs/corpus_flights.csv of the corpus branch) are all of its
#: tuning half: the judging half is never used here.
TESTLOGS: dict[str, tuple[str, str, str, str]] = {
    # PX4 1.9.0-beta, Pixhawk (FMU v3) quad 4006, UAVCAN ESCs (actuator_outputs[1], raw 0..8191) with a
    # mixer idle of 0.3, AUTO_MISSION + RTL, 38 s: vehicle_attitude rates, trajectory_setpoint x,y,z
    "auterion_v3_esc_status": ("Auterion/px4-ulog-rs", "f98b1045436e1a50430d13b995709c480e3854db",
                               "tests/fixtures/esc_status_log.ulg", "bc0690479c4df0936aee3b15a18ab2e630cf62d5"),
    # PX4 1.12.3-dev, FMU v5 quad 4011, an 8 s hand-flown hop without GPS
    "roboto_v5_test": ("roboto-ai/robologs-px4-actions", "36bc61bd7ee236f901aad857302b8b7992fc3db1",
                       "actions/px4_flight_review/test/input/test.ulg", "6196e983b2597d38de6e7b74a1d1018772bed598"),
    # PX4 1.9.0-dev, FMU v5 quad 4060, armed 5 s on the ground: PWM_MIN/MAX, vehicle_attitude rates
    "toopazo_v5_log156": ("toopazo/toopazo_ulg", "0d997da2698f6fa753c86ecec9e43b34866184b8",
                          "tests/logs/log_156_2020-12-15-12-32-12.ulg", "458807f59e7a750dcfce9a0f45cbb3f6872189d9"),
    # PX4 1.13.2-dev, FMU v5 quad 4001, mixer era (SYS_CTRL_ALLOC 0), never armed; current_a = -inf
    "mch_v5_test2": ("mengchaoheng/PX4_ulog_plottools", "81792ba62cf7f73627d14f02a1fde2a00b2faa8d",
                     "test2.ulg", "d4c83d114525f205fa5c661b5881e7290f3a704f"),
    # PX4 1.6-dev, FMU v4pro quad 4001 (not in the corpus): same old layout, armed but landed throughout
    "pyulog_sample_appended_multiple": (
        "PX4/pyulog", "dd44f431deb1f9b2075b7d513d41073b459b1109", "test/sample_appended_multiple.ulg",
        "760a80ffad47ed27f5a2ffc6d006bc4fbb9be0ea"),
}


def cache_dir() -> Path:
    env = os.environ.get("ROTORTWIN_TESTLOGS", "").strip()
    return Path(env) if env else Path.home() / ".cache" / "rotortwin" / "testlogs"


def corpus_tuning_dir() -> Path:
    """The corpus cache's tuning half (tools/corpus_fetch.py of the corpus branch): the same logs under
    their corpus id; its judging half is never looked at."""
    env = os.environ.get("ROTORTWIN_CORPUS", "").strip()
    return (Path(env) if env else Path.home() / ".cache" / "rotortwin" / "corpus") / "tuning"


def testlog_path(name: str) -> Path:
    p = cache_dir() / f"{TESTLOGS[name][3]}.ulg"
    alt = corpus_tuning_dir() / f"{name}.ulg"
    return p if p.is_file() or not alt.is_file() else alt


def need_testlog(name: str) -> Path:
    """The cached log ``name``, or a skip naming what is missing and how to fetch it."""
    p = testlog_path(name)
    if not p.is_file():
        repo, _, path, blob = TESTLOGS[name]
        pytest.skip(f"{name} ({repo}:{path}, blob {blob[:10]}) not in {cache_dir()}: "
                    "python tools/fetch_testlogs.py")
    return p
