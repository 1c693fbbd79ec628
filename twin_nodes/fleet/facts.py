"""What one log says about the vehicle, independent of any params file: the flight's kind, the motor
PWM range the firmware used, the values identified on it (each with its standard error) and the
firmware parameters, so a fleet can follow one vehicle across its flights (issue 25).

Pure functions of a :class:`~twin_nodes.logs.ulog_io.FlightLog` (and, for actuator tests, the ULog's
``vehicle_command``); the catalog stores what they return, the report and ``params from-ulog`` pool it.

Flight kinds (:func:`flight_kind`):

- ``free flight``: airborne with horizontal velocity, long enough to identify on (an airborne stretch over
  6 s, as :func:`twin_nodes.identify.nominal.nominal_from_log` needs);
- ``ground/bench test``: never airborne (land detector), or actuator/motor test commands in the log
  (``DO_SET_ACTUATOR`` 187, ``MAV_CMD_ACTUATOR_TEST`` 310, ``DO_MOTOR_TEST`` 209) while the height changed by
  less than 1 m;
- ``too short``: airborne, but too briefly for any identification;
- ``no GPS``: airborne without horizontal velocity or position.

Values (:data:`FACTS`, name -> (unit, meaning)); ``<name>_se`` is the standard error where the fit gives one.
``kt_per_mass`` and ``hover_throttle`` carry the thrust per mass: a payload and a weaker propulsion both
lower it; the roll/pitch control effectiveness ``T_max/I`` is the one value that tells them apart (a payload
near the centre of mass leaves it, a weaker propulsion lowers it by the same factor) -- see
:func:`twin_nodes.fleet.changes.explain`.
"""

from __future__ import annotations

import json
import math
from typing import Any, Callable

import numpy as np

from twin_nodes.base.constants import G_STANDARD_M_S2
from twin_nodes.base.errors import LogError, TwinError
from twin_nodes.logs.ulog_io import FlightLog

#: value name -> (unit, meaning)
FACTS = {
    "kt_per_mass": ("m/s^2", "thrust per mass at full command, per rotor (T_max/m, specific force z); kept where the "
                             "thrust/weight it implies is 1.05-10 (TW_RANGE)"),
    "hover_throttle": ("-", "median motor command in steady flight (v < 2 m/s)"),
    "hover_thrust_px4": ("-", "PX4's own hover thrust estimate (median, hover_thrust_estimate)"),
    "roll_eff": ("1/s^2", "roll control effectiveness T_max/Ixx (moment from commands vs angular acceleration)"),
    "pitch_eff": ("1/s^2", "pitch control effectiveness T_max/Iyy"),
    "rp_eff": ("1/s^2", "roll and pitch control effectiveness together (their mean): tells mass from thrust"),
    "yaw_eff": ("1/s^2", "yaw control effectiveness T_max km/Izz (km assumed 0.02 m: a relative value)"),
    "drag_per_mass": ("1/s", "horizontal linear drag per mass (drag / assumed mass)"),
    "com_dx_m": ("m", "roll/pitch trim as a centre-of-mass offset, body x (forward)"),
    "com_dy_m": ("m", "roll/pitch trim as a centre-of-mass offset, body y (left)"),
    "yaw_lever_m": ("m", "yaw trim of the median motor outputs as a lever (rotor tilt)"),
    "tau_s": ("s", "motor lag that explains roll/pitch accelerations best (NaN where not identified)"),
    "battery_v_start": ("V", "pack voltage at take-off"),
    "battery_v_min": ("V", "lowest pack voltage while airborne"),
    "battery_exponent": ("-", "thrust ~ (V/V_ref)^e: the sag exponent, where identified"),
}
#: a thrust fit is kept when the thrust/weight at full command it implies is in this range (the vehicle flew, and
#: no multirotor carries ten times its weight) and the steady throttle is at least HOVER_MIN
TW_RANGE = (1.05, 10.0)
HOVER_MIN = 0.05
#: a control effectiveness is kept when its standard error is below this fraction of it (the yaw one also needs
#: its fit to explain YAW_R2_MIN of the moment)
EFF_REL_SE_MAX = 0.25
YAW_R2_MIN = 0.2
#: commands that drive actuators on the ground: DO_MOTOR_TEST, DO_SET_ACTUATOR, MAV_CMD_ACTUATOR_TEST
ACTUATOR_TEST_COMMANDS = {209, 187, 310}
#: firmware parameters that change how a command becomes thrust or how the vehicle is flown: a change
#: between two flights of a vehicle is an event on its trend axis
EVENT_PREFIXES = ("PWM_MAIN_MIN", "PWM_MAIN_MAX", "PWM_AUX_MIN", "PWM_AUX_MAX", "PWM_MAIN_FUNC", "PWM_AUX_FUNC",
                  "MC_ROLLRATE_", "MC_PITCHRATE_", "MC_YAWRATE_", "MC_ROLL_P", "MC_PITCH_P", "MC_YAW_P",
                  "MPC_THR_HOVER", "MPC_THR_MAX", "MPC_THR_MIN", "THR_MDL_FAC", "CA_ROTOR", "BAT1_N_CELLS",
                  "BAT1_V_CHARGED", "BAT1_V_EMPTY", "SYS_AUTOSTART", "MPC_USE_HTE")
#: parameters that are noise for a comparison (calibrations, counters, statistics)
IGNORED_PREFIXES = ("CAL_", "SENS_", "LND_FLIGHT_T", "COM_FLIGHT_UUID", "BAT1_V_LOAD_DROP", "EKF2_MAGBIAS",
                    "EKF2_GYRBIAS", "EKF2_ACCBIAS", "EKF2_BARO_", "FW_", "SYS_HITL", "MAV_USEHILGPS")


def actuator_tests(path: str, side: Callable[[], Any] | None = None) -> int:
    """Number of actuator/motor test commands (:data:`ACTUATOR_TEST_COMMANDS`) in the log's
    ``vehicle_command`` (0 when it has none or the topic is absent; ``side``: the fleet runner's
    :func:`~twin_nodes.fleet.identity.side_reader`, read once for this and the GPS time)."""
    from pyulog import ULog

    u = side() if side is not None else None
    if u is None:
        try:
            u = ULog(str(path), ["vehicle_command"])
        except Exception:  # unreadable topic data: no evidence either way
            return 0
    n = 0
    for d in u.data_list:
        if d.name != "vehicle_command":
            continue
        cmd = d.data.get("command")
        if cmd is not None:
            n += int(np.isin(np.asarray(cmd, int), list(ACTUATOR_TEST_COMMANDS)).sum())
    return n


def height_change_m(log: FlightLog) -> float:
    """Range of the local height over the log [m] (0 without a finite height)."""
    pos = log.get("position_enu")
    if pos is None or not len(pos):
        return 0.0
    z = pos.values[:, 2]
    z = z[np.isfinite(z)]
    return float(z.max() - z.min()) if z.size else 0.0


def flight_kind(log: FlightLog, n_actuator_tests: int = 0) -> tuple[str, str]:
    """``(kind, why)``: one of ``free flight``, ``ground/bench test``, ``too short``, ``no GPS`` (see the module
    docstring); ``why`` is the one-line reason for every kind but a free flight."""
    from twin_nodes.logs.flyable import check_flyable

    dz = height_change_m(log)
    if n_actuator_tests and dz < 1.0:
        return "ground/bench test", (f"{log.path}: vehicle_command: {n_actuator_tests} actuator/motor test "
                                     f"command(s) and a height change of {dz:.2f} m: a ground or bench test")
    try:
        check_flyable(log)
    except LogError as exc:
        msg = str(exc)
        if "never airborne" in msg:
            return "ground/bench test", msg
        if "without GPS" in msg or "horizontal" in msg:
            return "no GPS", msg
        return "too short", msg
    longest = max((b - a for a, b in log.airborne_intervals()), default=0.0)
    if longest <= 6.0:
        return "too short", (f"{log.path}: landed: airborne for {longest:.1f} s at most: expected an airborne "
                             "stretch over 6 s to identify on")
    return "free flight", ""


def motor_pwm(params: dict[str, float], n_motors: int) -> dict[str, Any]:
    """The PWM range of the outputs assigned to motors (``PWM_MAIN_FUNCn`` / ``PWM_AUX_FUNCn`` = 101..):
    ``{"text": "MAIN1-4 1000-2000 us", "min_us", "max_us"}`` (min/max NaN where the motor outputs differ,
    or where no output group assigns the motors, e.g. DShot or UAVCAN ESCs)."""
    groups: dict[tuple[str, float, float], list[int]] = {}
    outputs: dict[str, list[str]] = {}
    limits: dict[str, list[float]] = {}
    for prefix in ("PWM_MAIN", "PWM_AUX"):
        for ch in range(1, 17):
            f = params.get(f"{prefix}_FUNC{ch}")
            if f is not None and 101 <= int(f) < 101 + max(n_motors, 1):
                lo, hi = params.get(f"{prefix}_MIN{ch}", math.nan), params.get(f"{prefix}_MAX{ch}", math.nan)
                groups.setdefault((prefix[4:], float(lo), float(hi)), []).append(ch)
                outputs.setdefault(f"m{int(f) - 100}", []).append(f"{prefix[4:]}{ch}")
                limits[f"{prefix[4:]}{ch}"] = [float(lo), float(hi)]
    if not groups:
        return {"text": "no PWM output assigned to the motors", "min_us": math.nan, "max_us": math.nan,
                "outputs": {}, "limits": {}}
    text = "; ".join(f"{g}{chs[0]}-{chs[-1]} {lo:.0f}-{hi:.0f} us" if math.isfinite(lo) and math.isfinite(hi) else
                     f"{g}{chs[0]}-{chs[-1]} (no PWM limits in the parameters)"
                     for (g, lo, hi), chs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[1])))
    ranges = {(lo, hi) for (_g, lo, hi) in groups}
    lo, hi = ranges.pop() if len(ranges) == 1 else (math.nan, math.nan)
    return {"text": text, "min_us": lo, "max_us": hi, "outputs": dict(sorted(outputs.items())), "limits": limits}


def assignment_text(pwm: dict) -> str:
    """Which outputs drive the motors, without their PWM limits (``MAIN1-4``, ``AUX1-4 + MAIN1-4`` where every
    motor is assigned to two outputs), from :func:`motor_pwm`; the PWM text's groups for a dict without outputs."""
    outs = pwm.get("outputs")
    if not outs:
        return "; ".join(seg.split(" ")[0] for seg in str(pwm.get("text", "")).split("; "))
    groups: dict[str, list[int]] = {}
    for o in sorted({o for v in outs.values() for o in v}):
        g = o.rstrip("0123456789")
        groups.setdefault(g, []).append(int(o[len(g):]))
    return " + ".join(f"{g}{min(c)}-{max(c)}" if len(c) > 1 else f"{g}{c[0]}" for g, c in sorted(groups.items()))


def shares_outputs(a: dict, b: dict) -> bool:
    """Every motor driven by an output both :func:`motor_pwm` dicts assign to it (one wiring)."""
    oa, ob = a.get("outputs") or {}, b.get("outputs") or {}
    return set(oa) == set(ob) and all(set(oa[m]) & set(ob[m]) for m in oa)


def same_configuration(a: dict, b: dict) -> tuple[bool, str]:
    """Whether two flights' motor outputs (:func:`motor_pwm` dicts) are one configuration of the vehicle: every
    motor driven by an output both assign to it with the same PWM limits in both (an output assigned besides, e.g.
    AUX1-4 mirroring MAIN1-4, may be connected to nothing: a log cannot tell which one is).  Another output
    assignment is another wiring (on the shared real fleet the yaw trim changed sign with it), another PWM range
    another thrust for the same command.  Returns (same, why not); dicts without ``outputs`` (older twins and
    catalogs) compare by their text."""
    oa, ob = a.get("outputs"), b.get("outputs")
    if not oa or not ob:
        same = a.get("text") == b.get("text")
        return same, "" if same else f"motor PWM range {b.get('text')}, the twin's is {a.get('text')}"
    if not shares_outputs(a, b):
        return False, f"motor outputs {assignment_text(b)}, the twin's are {assignment_text(a)} (another wiring)"
    la, lb = a.get("limits") or {}, b.get("limits") or {}
    def lim(d: dict, o: str) -> list:
        return [None if x != x else x for x in d.get(o, [])]  # NaN (no limit in the parameters) equal to NaN

    if any(not any(lim(la, o) == lim(lb, o) for o in set(oa[m]) & set(ob[m])) for m in oa):
        return False, (f"motor PWM range {b.get('text')}, the twin's is {a.get('text')} (the same command is "
                       "another thrust)")
    return True, ""


def param_changes(prev: dict[str, float] | None, cur: dict[str, float]) -> dict[str, list]:
    """``{name: [before, after]}`` for every parameter that differs (``None`` where absent), without
    :data:`IGNORED_PREFIXES`; ``{}`` when there is no previous flight."""
    if prev is None:
        return {}
    out = {}
    for k in sorted(set(prev) | set(cur)):
        if k.startswith(IGNORED_PREFIXES):
            continue
        a, b = prev.get(k), cur.get(k)
        if a is None or b is None or not math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-9):
            out[k] = [a, b]
    return out


def is_event(name: str) -> bool:
    """Whether a parameter change is drawn as an event on the trend axis (:data:`EVENT_PREFIXES`)."""
    return name.startswith(EVENT_PREFIXES)


def _battery(log: FlightLog) -> dict[str, float]:
    bv = log.get("battery_v")
    iv = log.airborne_intervals()
    if bv is None or not len(bv) or not iv:
        return {}
    v, t = bv.values[:, 0], bv.t_s
    air = np.zeros(t.size, bool)
    for a, b in iv:
        air |= (t >= a) & (t <= b)
    va = v[air & np.isfinite(v)]
    before = v[(t <= iv[0][0]) & np.isfinite(v)]
    out = {}
    if before.size:
        out["battery_v_start"] = float(before[-5:].mean())
    if va.size:
        out["battery_v_min"] = float(va.min())
        out.setdefault("battery_v_start", float(va[:5].mean()))
    return out


def identified(log: FlightLog, nom=None, build=None) -> dict[str, float]:
    """The values of :data:`FACTS` identified on a free flight (with ``<name>_se``), from the nominal built
    from the log (:func:`twin_nodes.identify.nominal.nominal_from_log`, the airframe's assumed mass; every value
    here is independent of it but ``drag_per_mass``'s scale); ``build``: a callable giving that nominal
    (:func:`~twin_nodes.identify.nominal.nominal_once`), used when ``nom`` is not given."""
    from twin_nodes.identify.nominal import nominal_from_log

    if nom is None:
        try:
            nom = build() if build is not None else nominal_from_log(log)
        except TwinError as exc:  # params that fail validation (e.g. cannot lift the assumed mass): fits kept
            if not hasattr(exc, "fits"):
                raise
            f = exc.fits
        else:
            f = nom.fits
    else:
        f = nom.fits
    m = f["mass_assumed_kg"]
    n = sum(1 for k in f if k.startswith("motor_share_m"))
    tw = n * f["kT/m"] / G_STANDARD_M_S2
    steady = _steady_throttle(log)
    if not TW_RANGE[0] <= tw <= TW_RANGE[1] or (steady is not None and steady[0] < HOVER_MIN):
        raise TwinError(f"{log.path}: specific_force_flu: implausible thrust fit (thrust/weight at full command "
                        f"{tw:.2f}, expected {TW_RANGE[0]}-{TW_RANGE[1]}; steady throttle "
                        f"{steady[0] if steady else float('nan'):.3f}): no values kept from this flight")
    out = {"kt_per_mass": f["kT/m"], "kt_per_mass_se": f["kT/m_se"]}
    if f["drag_n_s_m"] > 2 * f["drag_n_s_m_se"]:
        out["drag_per_mass"], out["drag_per_mass_se"] = f["drag_n_s_m"] / m, f["drag_n_s_m_se"] / m
    for k in ("com_dx_m", "com_dy_m", "yaw_lever_m", "battery_exponent", "battery_exponent_se"):
        if k in f:
            out[k] = f[k]
    for k, r2 in (("roll_eff", "roll_r2"), ("pitch_eff", "pitch_r2"), ("yaw_eff", "yaw_r2")):
        ok = math.isfinite(f.get(k, math.nan)) and f[k] > 0 and f[f"{k}_se"] <= EFF_REL_SE_MAX * f[k]
        if ok and (k != "yaw_eff" or f.get(r2, 0.0) >= YAW_R2_MIN):
            out[k], out[f"{k}_se"] = f[k], f[f"{k}_se"]
    if "roll_eff" in out and "pitch_eff" in out:  # the two together: less noise
        out["rp_eff"] = 0.5 * (out["roll_eff"] + out["pitch_eff"])
        out["rp_eff_se"] = 0.5 * math.hypot(out["roll_eff_se"], out["pitch_eff_se"])
    out["tau_s"] = f["tau_s"] if not f["tau_at_edge"] and f["tau_near_hi_s"] - f["tau_near_lo_s"] <= 0.08 else math.nan
    out.update({k: v for k, v in f.items() if k.startswith("motor_share_m")})
    if steady is not None:
        out["hover_throttle"], out["hover_throttle_se"] = steady
    ht = log.get("hover_thrust")
    if ht is not None and len(ht):
        h = ht.values[:, 0]
        h = h[np.isfinite(h)]
        if h.size:
            out["hover_thrust_px4"] = float(np.median(h))
    return out


def _steady_throttle(log: FlightLog) -> tuple[float, float] | None:
    """(median, its se) of the mean motor command while airborne and slower than 2 m/s, 1 s from take-off."""
    mot, vel = log.get("motors"), log.get("velocity_enu")
    if mot is None or vel is None or not len(mot):
        return None
    t = mot.t_s
    air = np.zeros(t.size, bool)
    for a, b in log.airborne_intervals():
        air |= (t >= a + 1.0) & (t <= b - 1.0)
    speed = np.linalg.norm(vel.at(t), axis=1)
    vals = np.asarray(mot.values, float)
    cnt = np.isfinite(vals).sum(axis=1)
    u = np.where(cnt > 0, np.nansum(vals, axis=1) / np.maximum(cnt, 1), np.nan)
    sel = air & (speed < 2.0) & np.isfinite(u)
    if sel.sum() < 20:
        return None
    x = u[sel]
    mad = 1.4826 * float(np.median(np.abs(x - np.median(x))))
    return float(np.median(x)), 1.25 * mad / math.sqrt(x.size / 10.0)  # ~10 independent samples per s at most


def flight_facts(path: str, log: FlightLog, side: Callable[[], Any] | None = None,
                 build: Callable[[], Any] | None = None) -> dict[str, Any]:
    """Catalog columns for one log: ``flight_kind``, ``kind_reason``, ``motor_pwm``, ``motor_pwm_min_us``,
    ``motor_pwm_max_us``, ``params_json`` (every firmware parameter), ``fact_<name>`` (+ ``_se``) for a free
    flight, the battery values for any airborne log, and ``facts_error`` where the identification failed;
    ``build``: the log's nominal (:func:`~twin_nodes.identify.nominal.nominal_once`), shared with its params."""
    n_tests = actuator_tests(path, side)
    kind, why = flight_kind(log, n_tests)
    pwm = motor_pwm(log.params, int(log.n_motors))
    row: dict[str, Any] = {"flight_kind": kind, "kind_reason": why, "actuator_tests": n_tests,
                           "motor_pwm": pwm["text"], "motor_outputs": assignment_text(pwm),
                           "motor_pwm_min_us": pwm["min_us"],
                           "motor_pwm_max_us": pwm["max_us"], "params_json": json.dumps(log.params, sort_keys=True),
                           "height_change_m": height_change_m(log)}
    vals = _battery(log)
    if kind == "free flight":
        try:
            vals.update(identified(log, build=build))
        except (TwinError, ValueError, np.linalg.LinAlgError) as exc:
            row["facts_error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    for k, v in vals.items():
        if isinstance(v, (int, float)) and math.isfinite(float(v)):
            row[f"fact_{k}"] = float(v)
    return row
