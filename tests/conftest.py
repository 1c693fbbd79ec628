"""Shared test fixtures: where the shared flight logs live.

The ULog files are never copied into the repo (no licence); tests read them from
``../shared/flightlogs/{real,sitl}`` next to the repository.  Without that
folder the tests that need it are skipped, except under ``CI=true``, where they
fail: CI must run them.

Use::

    def test_x(shared_dir): ...                      # Path to ../shared
    def test_y(real_logs, sitl_logs): ...            # lists of Paths (non-empty)

    from conftest import ulog_params, need_log
    @pytest.mark.parametrize("log", ulog_params("real") + ulog_params("sitl"))
    def test_z(log):
        path = need_log(log)                          # skip/fail if the folder is absent
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DIR = Path(__file__).resolve().parents[1].parent / "shared"
FLIGHTLOGS_DIR = SHARED_DIR / "flightlogs"


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def missing_shared(what: str) -> None:
    """Skip (locally) or fail (under CI=true) because shared data is absent."""
    msg = f"{what} not found under {SHARED_DIR}"
    if in_ci():
        pytest.fail(f"{msg} (CI=true: shared flight logs are required)")
    pytest.skip(msg)


def _logs(sub: str) -> list[Path]:
    d = FLIGHTLOGS_DIR / sub
    return sorted(d.glob("*.ulg")) if d.is_dir() else []


REAL_LOGS: list[Path] = _logs("real")
SITL_LOGS: list[Path] = _logs("sitl")


def ulog_params(sub: str) -> list:
    """pytest params, one per ``.ulg`` in ``flightlogs/<sub>`` (id = file stem).

    With the folder absent this is a single ``None`` param: pass it through
    :func:`need_log`, which skips or fails (CI) instead of silently running nothing."""
    files = _logs(sub)
    if files:
        return [pytest.param(f, id=f.stem) for f in files]
    return [pytest.param(None, id=f"{sub}-logs-missing")]


def need_log(path: Path | None) -> Path:
    if path is None:
        missing_shared("flight logs")
    assert path is not None
    return path


def shared_log(sub: str, name: str) -> Path:
    """Path of one named shared log (skip/fail like the fixtures if absent)."""
    p = FLIGHTLOGS_DIR / sub / name
    if not p.is_file():
        missing_shared(f"flightlogs/{sub}/{name}")
    return p


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED_DIR.is_dir():
        missing_shared("shared folder")
    return SHARED_DIR


@pytest.fixture(scope="session")
def real_logs() -> list[Path]:
    if not REAL_LOGS:
        missing_shared("flightlogs/real/*.ulg")
    return list(REAL_LOGS)


@pytest.fixture(scope="session")
def sitl_logs() -> list[Path]:
    if not SITL_LOGS:
        missing_shared("flightlogs/sitl/*.ulg")
    return list(SITL_LOGS)


def px4_sitl_binary() -> Path:
    """The PX4 SITL binary under ``$PX4_DIR``; skips (one line) when it is not set or not built."""
    px4_dir = os.environ.get("PX4_DIR", "")
    if not px4_dir:
        pytest.skip("PX4_DIR not set (a PX4-Autopilot checkout built with make px4_sitl_default)")
    b = Path(px4_dir) / "build" / "px4_sitl_default" / "bin" / "px4"
    if not b.is_file():
        pytest.skip(f"{b} not found: build PX4 SITL first (make px4_sitl_default)")
    return b


#: where :func:`sih_quadx_flight`'s topics start (their timestamps, microseconds)
SIM_START_US = 20_000_000


@pytest.fixture(scope="session")
def sih_quadx_flight():
    """Our simulator's no-effect flight of the shipped PX4 SIH quad X (seed 3) as PX4 topics from
    :data:`SIM_START_US`: ``(vehicle params, topics)``.  Read-only: a test that edits topics copies them."""
    import numpy as np

    from twin_nodes.twin.simflight import Hidden, record_to_topics, simulate_flight
    from twin_nodes.vehicle.params import shipped

    vp = shipped("px4_sih_quadx")
    rec, battery, sp_hist = simulate_flight(vp, Hidden("none", {}), seed=3)
    return vp, record_to_topics(rec, vp, battery, sp_hist, np.random.default_rng(10), start_us=SIM_START_US)
