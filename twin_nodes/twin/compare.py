"""Twin versus real: put both on one grid and compute the Table-2 metrics (pure; no ROS).

The same functions serve the offline path (``compare_log``: a whole ULog through
:func:`twin_nodes.twin.runner.run_twin_on_log`) and the live graph (the metrics node
builds a :class:`~twin_nodes.logs.ulog_io.FlightLog` and a
:class:`~twin_nodes.twin.runner.TwinRun` from the topics it received and calls
:func:`align` + :func:`~twin_nodes.twin.metrics.flight_metrics` at the end), so the
numbers are computed one way only.

What is compared (twin minus real):

- XY, Z: twin position vs the real (EKF) ``position_enu``.
- throttle: the twin's collective thrust command (``TwinRun.throttle``) vs the
  real ``throttle`` series (PX4 ``vehicle_thrust_setpoint``; on PX4 <= 1.13
  ``actuator_controls_0[3]``).
- motors: the twin's motor commands vs the real ``motors`` (0..1, PX4 order).

Modes: ``closed`` — our PX4-like controller flies the real setpoints (the
paper's method).  ``open`` — the real motor commands drive the model, re-synced
to the real state every ``horizon_s``: XY/Z are then the re-synced prediction
errors, and the twin's motors *are* the real ones by construction (their errors
are zero and say nothing); the twin's throttle is the mean real motor command.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from twin_nodes.logs import time_sync
from twin_nodes.twin.metrics import Aligned, flight_metrics
from twin_nodes.twin import divergence
from twin_nodes.twin.estimate_check import estimate_failed
from twin_nodes.twin.flight_mode import controlled_axes
from twin_nodes.twin.runner import TwinRun, run_twin_on_log

__all__ = ["align", "compare_log", "load_flight", "CompareResult", "OPEN_LOOP_NOTE", "DEFAULT_RATE_HZ", "mask_from_intervals",
           "streams_to_log_and_run", "metrics_from_streams"]

#: default comparison grid [Hz] (the Table-2 numbers are computed on it)
DEFAULT_RATE_HZ = 50.0
OPEN_LOOP_NOTE = ("open loop: XY/Z errors are re-synced prediction errors (re-sync every horizon_s); the twin's "
                  "motor commands are the real ones by construction (held at the twin rate, so motor errors "
                  "only show resampling), its throttle is the mean real motor command")


#: the series the twin flies beside (``inputs.log_inputs``): a log without one of them is refused
TWIN_INPUTS = ("position_enu", "velocity_enu", "attitude_q", "body_rates_flu", "motors")


def load_flight(path: Any) -> Any:
    """The flight to compare, loaded and checked once, the same way for the offline and the graph
    mode (the graph's parent process calls it before starting any node, so its loader warnings and
    its refusals are the offline ones): :func:`twin_nodes.logs.flyable.read_flight` (value checks,
    time repairs, too short / never airborne / never left the ground; a flight without GPS is flown
    and scored on what it has: Z, throttle, motors) and every series
    the twin needs (:data:`TWIN_INPUTS`), else a one-line :class:`~twin_nodes.base.errors.LogError`."""
    from twin_nodes.logs.flyable import read_flight

    log = read_flight(path, horizontal=False)  # flown and scored on what it has (no XY without GPS)
    for name in TWIN_INPUTS:
        log.require(name)
    return log


@dataclass
class CompareResult:
    metrics: dict[str, Any]
    aligned: Aligned
    run: TwinRun


def mask_from_intervals(t: np.ndarray, intervals: list[tuple[float, float]]) -> np.ndarray:
    """Boolean mask of the times inside any ``[start, end]`` interval."""
    t = np.asarray(t, float)
    m = np.zeros(t.shape, bool)
    for a, b in intervals:
        m |= (t >= a) & (t <= b)
    return m


def _as_logged(t_src: np.ndarray, values: np.ndarray, real: Any, t: np.ndarray) -> np.ndarray:
    """Twin series ``values`` seen through the real series' logging: sampled at its timestamps,
    then interpolated onto ``t`` like the real one (plain interpolation when the log has none)."""
    if real is None or len(real) < 2:
        return _interp(t_src, values, t)
    at_log = _interp(t_src, values, np.asarray(real.t_s, float))
    return time_sync.interp_to(np.asarray(real.t_s, float), at_log, t, kind="linear")


#: height above the take-off / touchdown point below which the ends of a flight are not scored [m]
GROUND_MARGIN_M = 0.5
#: the longest a ground phase lasts [s]: spool-up and lift-off, or touchdown and the land detector's 2-4 s lag,
#: take seconds; a longer stretch within the margin of an interval's end height is flight (an indoor hover
#: at 1.5 m whose airborne interval ends there, a log that ends in the air)
GROUND_PHASE_MAX_S = 8.0
#: an airborne interval that begins within this of the first height sample began before the data did [s]
_STARTED_AIRBORNE_S = 0.5


def ground_phases(t: np.ndarray, z_real: np.ndarray, intervals: list[tuple[float, float]],
                  margin_m: float = GROUND_MARGIN_M, *, flight: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> np.ndarray:
    """Samples at the ends of each airborne interval while the real vehicle is still within
    ``margin_m`` of where it took off (spool-up, lift-off) or already within ``margin_m`` of where
    it touched down (ground contact and the land detector's 2-4 s lag).  The twin models neither
    landing gear nor PX4's land logic, so these are excluded from the metrics (and said so).

    Where it took off and touched down are read from the whole flight's heights ``flight`` = (times, z)
    (default: ``t``, ``z_real`` themselves).  A window that starts or ends in the air (the held-out part)
    must pass the whole flight: measured from the window's own ends, its first seconds (until the vehicle
    rose 0.5 m above where the window began) were taken for a take-off.  Each phase lasts at most
    :data:`GROUND_PHASE_MAX_S`; an interval that begins with the data (a log, or a live stream, joined in the
    air) has no take-off phase, and one that ends with it has a touchdown only if the vehicle came down into
    its last height."""
    ft, fz = (np.asarray(t, float), np.asarray(z_real, float)) if flight is None else (
        np.asarray(flight[0], float), np.asarray(flight[1], float))
    out = np.zeros(t.shape, bool)
    for a, b in intervals:
        idx = np.flatnonzero((ft >= a) & (ft <= b) & np.isfinite(fz))
        if idx.size < 2:
            continue
        z = fz[idx]
        joined_airborne = a <= ft[0] + _STARTED_AIRBORNE_S  # a log or stream that begins in the air
        # an interval that ends with the data ends in a touchdown only if the vehicle came down into its last
        # height (1 m within the phase's length); else the log or stream stopped in the air
        last = ft[idx] >= b - GROUND_PHASE_MAX_S
        touchdown = b < ft[-1] - _STARTED_AIRBORNE_S or bool(np.any(z[last] > z[-1] + 2.0 * margin_m))
        up = np.flatnonzero(z > z[0] + margin_m)
        down = np.flatnonzero(z > z[-1] + margin_m)
        if (up.size == 0 and not joined_airborne) or (down.size == 0 and touchdown):
            continue  # never left the ground by the margin: nothing to trim, nothing to score safely
        if not joined_airborne:
            out |= (t >= a) & (t < min(ft[idx[up[0]]], a + GROUND_PHASE_MAX_S))
        if touchdown:
            out |= (t > max(ft[idx[down[-1]]], b - GROUND_PHASE_MAX_S)) & (t <= b)
    return out


def _interp(t_src: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    if len(t_src) == 0:
        shape = (len(t),) + np.asarray(values).shape[1:]
        return np.full(shape, np.nan)
    return time_sync.interp_to(np.asarray(t_src, float), np.asarray(values, float), t, kind="linear")


def align(run: TwinRun, log: Any, rate_hz: float = DEFAULT_RATE_HZ, t0: float | None = None,
          t1: float | None = None, airborne_only: bool = True, check_divergence: bool = True) -> Aligned:
    """Twin outputs and the real log on one uniform grid (via :mod:`twin_nodes.logs.time_sync`).

    The grid spans the overlap of the twin run and the real position (clipped to
    ``[t0, t1]`` when given).  ``mask`` keeps samples where both XY are finite
    and, with ``airborne_only``, the vehicle is airborne
    (:meth:`FlightLog.airborne_intervals`: land detector, else armed, else height).  XY and Z are
    scored only where PX4 controlled them (:func:`~twin_nodes.twin.flight_mode.controlled_axes`); a closed-loop
    twin is checked for a divergence from the real flight up to ``t1`` (:mod:`twin_nodes.twin.divergence`;
    the streamed graph's twin has no attitude: ``check_divergence=False``)."""
    pos = log.require("position_enu")
    if len(run.t) == 0:
        raise ValueError("align: the twin run has no samples (did the log have state data?)")
    lo = max(float(run.t[0]), float(pos.t_s[0]))
    hi = min(float(run.t[-1]), float(pos.t_s[-1]))
    if t0 is not None:
        lo = max(lo, float(t0))
    if t1 is not None:
        hi = min(hi, float(t1))
    if hi <= lo:
        raise ValueError(f"align: twin [{run.t[0]:.2f}, {run.t[-1]:.2f}] s and real position "
                         f"[{pos.t_s[0]:.2f}, {pos.t_s[-1]:.2f}] s do not overlap")
    t = time_sync.common_grid(lo, hi, rate_hz, source=str(getattr(log, "path", "<log>")))
    p_real = pos.at(t, "linear")
    x_twin = _interp(run.t, run.x[:, 0:3], t)
    thr = log.get("throttle")
    thr_real = thr.at(t, "linear")[:, 0] if thr is not None and len(thr) else np.full(len(t), np.nan)
    mot = log.get("motors")
    n = run.motors.shape[1]
    m_real = mot.at(t, "linear") if mot is not None and len(mot) else np.full((len(t), n), np.nan)
    if m_real.shape[1] != n:
        raise ValueError(f"align: the log has {m_real.shape[1]} motors, the twin {n}")
    # the twin's outputs are sampled where PX4 logged the real ones, then both are put on the grid
    # the same way: a 10 Hz motor log is compared with a 10 Hz view of the twin, not its 250 Hz loop
    thr_twin = _as_logged(run.t, run.throttle, thr, t)
    m_twin = _as_logged(run.t, run.motors, mot, t)
    # throttle and motors are scored wherever the twin flies; xy and z also need the real position
    # there (a flight without GPS has no horizontal one) and PX4 controlling that axis
    mask = np.all(np.isfinite(x_twin[:, :3]), axis=1)
    xy_c, z_c, how = controlled_axes(log, t)
    xy_mask = xy_c & np.all(np.isfinite(p_real[:, :2]), axis=1)
    z_mask = z_c & np.isfinite(p_real[:, 2])
    notes: list[str] = []
    if not xy_c.all() or not z_c.all():
        notes.append(f"xy and z scored only where PX4 controlled them ({how})")
    est_bad = estimate_failed(log, t)[0]
    if est_bad.any():
        notes.append(f"ESTIMATE FAILED: {est_bad.sum() / rate_hz:.1f} s where the vehicle's own position estimate is "
                     "inconsistent with its IMU or with itself, or its estimator rejected its measurements, left out "
                     "of xy and z (the real position there is not known)")
    if airborne_only:
        iv = log.airborne_intervals()
        if iv:
            mask &= mask_from_intervals(t, iv)
            flight_z = (np.asarray(pos.t_s, float), np.asarray(pos.values, float)[:, 2])
            ground = ground_phases(t, p_real[:, 2], iv, flight=flight_z) & mask
            if ground.any():
                mask &= ~ground
                notes.append(f"take-off/touchdown: {ground.sum() / rate_hz:.1f} s within {GROUND_MARGIN_M} m of the "
                             f"ground at the ends of {len(iv)} airborne interval(s) not scored (spool-up, ground "
                             f"contact and the land detector's lag; the twin models no landing gear or land logic)")
        else:
            notes.append("no airborne interval found: the whole overlap is compared")
    if run.mode == "open":
        notes.append(OPEN_LOOP_NOTE)
    pilot = (run.info or {}).get("pilot") or {}
    if pilot.get("s", 0.0) > 0.0:
        notes.append(f"manual modes: a pilot stand-in held the real height, {pilot['s']:.1f} s; its mean correction "
                     f"{100.0 * pilot['mean_correction_of_hover']:+.1f} % of hover (the collective the model lacks: "
                     "the throttle there is scored as logged + correction)")
    div = None
    if run.mode == "closed" and run.x.shape[1] >= 13 and check_divergence:
        iv_air = log.airborne_intervals()
        div = divergence.detect(run, log, xy_controlled=lambda tt: controlled_axes(log, tt)[0],
                                z_controlled=lambda tt: controlled_axes(log, tt)[1], t1=t1,
                                ground=lambda tt: ground_phases(tt, pos.at(tt, "linear")[:, 2], iv_air,
                                                                flight=(pos.t_s, np.asarray(pos.values)[:, 2])))
        if div is not None:
            notes.append(f"DIVERGED at {div['t_s']:.2f} s: {div['cause']} ({div['detail']}); the metrics after "
                         "it describe another flight")
    return Aligned(t=t, xy_twin=x_twin[:, :2], xy_real=p_real[:, :2], z_twin=x_twin[:, 2], z_real=p_real[:, 2],
                   throttle_twin=thr_twin, throttle_real=thr_real, motors_twin=m_twin, motors_real=m_real,
                   mask=mask, mode=run.mode, notes=notes, xy_mask=xy_mask, z_mask=z_mask, divergence=div,
                   estimate_failed=est_bad)


def compare_log(log: Any, vp: Any, mode: str = "closed", horizon_s: float = 2.0, airborne_only: bool = True,
                rate_hz: float = DEFAULT_RATE_HZ, progress: bool = False,
                setpoint_between_samples: bool = True) -> CompareResult:
    """Run the twin beside a whole log and compute the whole-flight metrics (``setpoint_between_samples``:
    :func:`~twin_nodes.twin.runner.run_twin_on_log`).

    ``log``: :class:`~twin_nodes.logs.ulog_io.FlightLog`; ``vp``: vehicle parameters.
    Returns :class:`CompareResult` with ``metrics`` (see
    :func:`~twin_nodes.twin.metrics.flight_metrics`), the aligned series and the run."""
    run = run_twin_on_log(log, vp, mode=mode, horizon_s=horizon_s, progress=progress,
                          setpoint_between_samples=setpoint_between_samples)
    al = align(run, log, rate_hz=rate_hz, airborne_only=airborne_only)
    m = flight_metrics(al)
    m["params"] = getattr(vp, "name", "")
    m["log"] = str(getattr(log, "path", ""))
    if mode == "open":
        m["horizon_s"] = float(horizon_s)
    if not math.isfinite(float(m.get("throttle_rmse", math.nan))) and log.get("throttle") is None:
        m.setdefault("notes", []).append("the log has no throttle series: throttle metrics are n/a")
    return CompareResult(metrics=m, aligned=al, run=run)


def _series_of(t: np.ndarray, v: np.ndarray, units: str, frame: str, source: str, interp: str = "linear"):
    from twin_nodes.logs.ulog_io import Series

    t = np.asarray(t, float)
    v = np.asarray(v, float).reshape(len(t), -1)
    if len(t) > 1:
        keep = np.concatenate([[True], np.diff(t) > 0])  # strictly increasing for time_sync
        t, v = t[keep], v[keep]
    return Series(t, v, units, frame, source, interp)


def streams_to_log_and_run(real: dict[str, tuple[np.ndarray, np.ndarray]], twin: dict[str, np.ndarray],
                           mode: str, n_motors: int, source: str = "topics") -> tuple[Any, TwinRun]:
    """A :class:`FlightLog` and a :class:`TwinRun` from received topic data (times in s).

    ``real``: ``{'position_enu': (t, (n,3)), 'throttle': (t, (n,)), 'motors': (t, (n,N)),
    'status': (t, (n,3) [armed, nav_state, landed])}`` (any may be missing);
    ``twin``: ``{'t': (m,), 'p': (m,3), 'throttle': (m,), 'motors': (m,N)}``.
    Used by the metrics node and ``rotortwin regress`` so that they compute the
    whole-flight metrics exactly like the offline :func:`compare_log`."""
    from twin_nodes.logs.ulog_io import FlightLog

    series = {}
    if "position_enu" in real:
        series["position_enu"] = _series_of(*real["position_enu"], "m", "ENU", source)
    if "throttle" in real:
        series["throttle"] = _series_of(*real["throttle"], "-", "-", source)
    if "motors" in real:
        series["motors"] = _series_of(*real["motors"], "-", "PX4 motor order", source)
    if "status" in real:
        t, v = real["status"]
        v = np.asarray(v, float).reshape(len(t), 3)
        for i, name in ((0, "armed"), (2, "landed")):
            ok = np.isfinite(v[:, i])
            if ok.any():
                series[name] = _series_of(np.asarray(t)[ok], v[ok, i], "-", "bool", source, "previous")
    t_all = [float(s.t_s[-1]) for s in series.values() if len(s)]
    log = FlightLog(path=source, start_us=0, duration_s=max(t_all) if t_all else 0.0, params={}, info={},
                    series=series, warnings=[], n_motors=n_motors)
    tt = np.asarray(twin["t"], float)
    x = np.zeros((len(tt), 13))
    x[:, 0:3] = np.asarray(twin["p"], float).reshape(len(tt), 3)
    x[:, 6] = 1.0
    run = TwinRun(t=tt, x=x, motors=np.asarray(twin["motors"], float).reshape(len(tt), n_motors),
                  throttle=np.asarray(twin["throttle"], float).reshape(len(tt)),
                  specific_force=np.zeros((len(tt), 3)), mode=mode)
    return log, run


def metrics_from_streams(real: dict[str, tuple[np.ndarray, np.ndarray]], twin: dict[str, np.ndarray], mode: str,
                         n_motors: int, rate_hz: float = DEFAULT_RATE_HZ, airborne_only: bool = True,
                         source: str = "topics") -> CompareResult:
    """Whole-flight metrics of received topic data (see :func:`streams_to_log_and_run`)."""
    log, run = streams_to_log_and_run(real, twin, mode, n_motors, source)
    al = align(run, log, rate_hz=rate_hz, airborne_only=airborne_only, check_divergence=False)
    return CompareResult(metrics=flight_metrics(al), aligned=al, run=run)
