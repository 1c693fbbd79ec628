"""Identification from flight logs: the log-facing half of ``rotortwin identify``.

One function per method takes a :class:`~twin_nodes.logs.ulog_io.FlightLog` (or a
bench CSV), optional :class:`~twin_nodes.vehicle.params.VehicleParams` and plain
options, feeds the log's series to the pure fits of the sibling modules and
returns a result from :mod:`twin_nodes.identify.results`:

- :func:`identify_motor` motor lag from command/RPM steps (:mod:`.step_response`);
- :func:`hover_flight` then :func:`hover_parameters` hover segments and ``kt`` (:mod:`.hover`);
- :func:`identify_delays` command -> response delays (:mod:`.delay`);
- :func:`identify_regression` equation-error least squares (:mod:`.regression`);
- :func:`identify_noise` IMU noise of the pre-arm ground segment (:mod:`.noise`).

Bad input raises :class:`~twin_nodes.base.errors.LogError` / ``ParamsError`` with
a one-line message.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from twin_nodes.base import frames
from twin_nodes.base.errors import LogError, ParamsError
from twin_nodes.identify import hover as hv
from twin_nodes.identify import noise as nz
from twin_nodes.identify import regression as rg
from twin_nodes.identify import step_response as sr
from twin_nodes.identify.delay import estimate_delay
from twin_nodes.identify.results import (DelayResult, HoverFlight, HoverResult, MotorFit, MotorResult, NoiseResult,
                                         RegressionData, RegressionResult, check_merged)
from twin_nodes.logs.flyable import check_flyable
from twin_nodes.identify.fit_mask import fit_mask
from twin_nodes.logs.ulog_io import FlightLog
from twin_nodes.vehicle.params import VehicleParams

# --------------------------------------------------------------------------- log adapters


def airborne_mask(log: FlightLog, t: np.ndarray) -> np.ndarray:
    """(n,) bool: ``t`` [s] inside one of the log's airborne intervals."""
    m = np.zeros(t.size, dtype=bool)
    for a, b in log.airborne_intervals():
        m |= (t >= a) & (t <= b)
    return m


def height_above_takeoff(log: FlightLog, t: np.ndarray, z_up: np.ndarray) -> np.ndarray:
    """Height [m] above the point each airborne interval started from (NaN outside intervals).

    ``t`` (n,) [s], ``z_up`` (n,) [m] height on the same grid; the take-off height is
    the last finite one at or before take-off, else the interval's first finite one.
    """
    h = np.full(t.size, np.nan)
    for a, b in log.airborne_intervals():
        sel = (t >= a) & (t <= b)
        before = np.flatnonzero((t <= a) & np.isfinite(z_up))
        z0 = z_up[before[-1]] if before.size else (z_up[sel][np.isfinite(z_up[sel])][:1].tolist() or [np.nan])[0]
        h[sel] = z_up[sel] - z0
    return h


def rotor_geometry(log: FlightLog, vp: VehicleParams | None) -> tuple[rg.RotorGeometry, str | None]:
    """Rotor geometry and a note on where it came from.

    The params file's rotors, else the log's ``CA_ROTORn_PX/PY/KM`` (body FRD [m] -> FLU),
    else, for 4 motors, the shape of PX4's generic quad X (arm 1 m).
    """
    if vp is not None:
        return rg.RotorGeometry.from_params(vp), None
    n = int(log.n_motors)
    p = log.params
    if all(f"CA_ROTOR{i}_PX" in p and f"CA_ROTOR{i}_PY" in p for i in range(n)):
        x = np.array([p[f"CA_ROTOR{i}_PX"] for i in range(n)])
        y_frd = np.array([p[f"CA_ROTOR{i}_PY"] for i in range(n)])
        km = np.array([p.get(f"CA_ROTOR{i}_KM", 0.05) for i in range(n)])
        pos_flu = frames.frd_to_flu(np.column_stack([x, y_frd, np.zeros(n)]))
        return (rg.RotorGeometry(pos_flu[:, 0], pos_flu[:, 1], np.where(km >= 0, 1.0, -1.0)),
                "rotor geometry from the log's CA_ROTORn_PX/PY/KM parameters")
    if n != 4:
        raise LogError(log.path, "CA_ROTORn_PX/PY",
                       f"expected rotor positions for {n} rotors (or --params); none in the log")
    return (rg.RotorGeometry.quad_x(1.0),
            "no CA_ROTORn_* in the log and no --params: PX4 generic quad X geometry assumed (shape only)")


def angular_accel(log: FlightLog, source: str = "rates") -> tuple[np.ndarray, np.ndarray, str]:
    """Angular acceleration: times (n,) [s], values (n, 3) [rad/s^2] body FLU, and a description.

    ``"rates"`` (default): central differences of the logged body rates at their
    own time stamps; any smoothing is left to the caller, which applies the same
    low-pass to both sides of a regression.  ``"px4"``: PX4's own
    ``xyz_derivative``; on these logs it is a 50 Hz *sample* of a ~1 kHz
    differentiated signal and aliases badly (R2 0.1 against 0.6 on the SIH log).
    """
    aa = log.get("angular_accel_flu")
    if source == "px4":
        if aa is None:
            raise LogError(log.path, "vehicle_angular_velocity.xyz_derivative",
                           "expected PX4's angular acceleration (PX4 >= v1.12); use --accel-source rates")
        return aa.t_s, aa.values, "angular_accel_flu (PX4 xyz_derivative)"
    br = log.require("body_rates_flu")
    ok = np.all(np.isfinite(br.values), axis=1)
    t = br.t_s[ok]
    return t, np.gradient(br.values[ok], t, axis=0), "d/dt body_rates_flu (central differences)"


@dataclass(frozen=True)
class DelayPair:
    """A command series (``t_cmd`` [s], ``cmd``) and the response it drives (``t_resp`` [s], ``resp``),
    with the lag window [``min_delay_s``, ``max_delay_s``] to search."""

    label: str
    t_cmd: np.ndarray
    cmd: np.ndarray
    t_resp: np.ndarray
    resp: np.ndarray
    min_delay_s: float
    max_delay_s: float


def delay_inputs(log: FlightLog, geometry: rg.RotorGeometry | None) -> dict[str, DelayPair]:
    """The command/response pairs this log has the series for, by name, in this order: ``thrust``,
    ``motors``, ``torque_roll/pitch/yaw``, ``motor_roll/pitch/yaw`` (these need ``geometry``), ``climb``."""
    out: dict[str, DelayPair] = {}
    thr, sf, mot = log.get("throttle"), log.get("specific_force_flu"), log.get("motors")
    if thr is not None and sf is not None:
        out["thrust"] = DelayPair("throttle -> specific force z", thr.t_s, thr.values[:, 0], sf.t_s, sf.values[:, 2],
                                  -0.1, 0.3)
    if mot is not None and sf is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all motors NaN while disarmed
            mean = np.nanmean(mot.values, axis=1)
        out["motors"] = DelayPair("mean motor command -> specific force z", mot.t_s, mean, sf.t_s, sf.values[:, 2],
                                  -0.1, 0.3)
    if log.get("body_rates_flu") is not None:
        ta, aa, src = angular_accel(log)
        tq = log.get("torque_setpoint_flu")
        axes = ("roll", "pitch", "yaw")
        if tq is not None:
            for k, ax in enumerate(axes):
                out[f"torque_{ax}"] = DelayPair(f"torque setpoint {ax} -> {src}", tq.t_s, tq.values[:, k], ta,
                                                aa[:, k], -0.1, 0.3)
        if mot is not None and geometry is not None:
            l = geometry.arm_length_m
            mix = (geometry.y_flu_m / l, -geometry.x_flu_m / l, -geometry.direction)  # roll, pitch, yaw
            for k, ax in enumerate(axes):
                out[f"motor_{ax}"] = DelayPair(f"motor differential {ax} -> {src}", mot.t_s, mot.values @ mix[k],
                                               ta, aa[:, k], -0.1, 0.3)
    sv, vel = log.get("setpoint_velocity_enu"), log.get("velocity_enu")
    if sv is not None and vel is not None:
        out["climb"] = DelayPair("velocity setpoint up -> velocity up", sv.t_s, sv.values[:, 2], vel.t_s,
                                 vel.values[:, 2], -0.5, 2.0)
    return out


# --------------------------------------------------------------------------- motor


def identify_motor(source: str, log: FlightLog | None, *, rate_hz: float = 30.0, fit_delay: bool = True,
                   max_delay_s: float = 0.5, symmetric: bool = False) -> MotorResult:
    """First-order motor model ``K/(tau s + 1)`` (+ delay) per motor, symmetric and up/down.

    ``log`` None: ``source`` is a bench CSV (``time_s,command,rpm``); else every motor of
    the log with ESC RPM is fitted.  ``rate_hz`` is the rate of the ZOH difference
    equation; ``symmetric`` writes the symmetric tau [s] as both ``tau_up_s`` and ``tau_down_s``.
    """
    notes: list[str] = []
    datasets: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    if log is not None:
        check_flyable(log, airborne=False, horizontal=False)  # a bench test is fine, a 1-sample log is not
    if log is None:
        t, u, rpm = sr.read_step_csv(source)
        datasets.append(("csv", t, u, t, rpm))
        u_label = "command"
    else:
        esc = log.get("esc_rpm")
        if esc is None or not np.any(np.isfinite(esc.values) & (esc.values != 0)):
            raise LogError(source, "esc_status.esc[].esc_rpm",
                           "expected ESC RPM telemetry to fit the motor response; this log has none "
                           "(use a bench CSV with columns time_s,command,rpm)")
        mot = log.require("motors")
        for i in range(min(mot.values.shape[1], esc.values.shape[1])):
            ok_u = np.isfinite(mot.values[:, i])
            if np.count_nonzero(ok_u) < 10:
                notes.append(f"motor {i + 1}: fewer than 10 finite commands, skipped")
                continue
            tu, u = mot.t_s[ok_u], mot.values[ok_u, i]
            ok_y = np.isfinite(esc.values[:, i]) & (esc.t_s >= tu[0]) & (esc.t_s <= tu[-1])
            if np.count_nonzero(ok_y) < 10:
                notes.append(f"motor {i + 1}: fewer than 10 RPM samples while commanded, skipped")
                continue
            datasets.append((f"motor{i + 1}", tu, u, esc.t_s[ok_y], esc.values[ok_y, i]))
        if not datasets:
            raise LogError(source, "esc_rpm", "expected at least 10 RPM samples while a motor is commanded")
        u_label = "actuator_motors command [0..1]"
        if "SITL" in str(log.info.get("ver_hw", "")):
            notes.append("SITL log: esc_status RPM is synthetic (PX4 SimulatorMavlink: control x 6000), "
                         "so this checks the pipeline, not a motor")

    fits = []
    for name, tu, u, ty, y in datasets:
        try:
            sym = sr.fit_step_response(tu, u, ty, y, asymmetric=False, fit_delay=fit_delay, max_delay_s=max_delay_s)
            asym = sr.fit_step_response(tu, u, ty, y, asymmetric=True, fit_delay=fit_delay, max_delay_s=max_delay_s)
        except ValueError as exc:
            raise LogError(source, name, str(exc)) from None
        disc = sr.discretize_zoh(sym.tau_s, sym.gain, rate_hz, delay_s=sym.delay_s, u_ref=sym.u_ref, y_ref=sym.y_ref)
        fits.append(MotorFit(name, tu, u, ty, y, sym, asym, disc))

    tau_up = float(np.median([f.asymmetric.tau_up_s for f in fits]))
    tau_dn = float(np.median([f.asymmetric.tau_down_s for f in fits]))
    if symmetric:
        tau_up = tau_dn = float(np.median([f.symmetric.tau_s for f in fits]))
    return MotorResult(source, rate_hz, u_label, fits, tau_up, tau_dn, notes)


# --------------------------------------------------------------------------- hover


def hover_flight(log: FlightLog, *, source: str | None = None, min_duration_s: float = 3.0,
                 max_vz_m_s: float = 0.3, max_vxy_m_s: float = 0.5, max_az_m_s2: float = 0.5,
                 min_height_m: float = 1.0) -> HoverFlight:
    """Steady-hover segments of an airborne log on a 10 Hz grid (thresholds: see :func:`.hover.hover_mask`).

    ``source`` names the log in messages and the report (default ``log.path``).
    """
    source = log.path if source is None else source
    check_flyable(log)
    names = ["velocity_enu", "throttle", "position_enu"]
    opt = [n for n in ("attitude_q", "motors", "esc_rpm", "hover_thrust") if log.get(n) is not None]
    for n in names:
        log.require(n)
    t, v = log.resample(names + [n for n in opt if n != "hover_thrust"], 10.0)
    hte = log.get("hover_thrust").at(t) if "hover_thrust" in opt else None
    air = airborne_mask(log, t)
    if not np.any(air):
        raise LogError(source, "landed", "expected an airborne stretch (land detector), found none")
    motors = v.get("motors")
    rpm = v.get("esc_rpm")
    height = height_above_takeoff(log, t, v["position_enu"][:, 2])
    segs = hv.detect_hover_segments(
        t, v["velocity_enu"], v["throttle"][:, 0], airborne=air, attitude_q=v.get("attitude_q"),
        height_m=height, min_height_m=min_height_m,
        motors=motors, rpm=rpm, min_duration_s=min_duration_s, max_vz_m_s=max_vz_m_s,
        max_vxy_m_s=max_vxy_m_s, max_az_m_s2=max_az_m_s2)
    if not segs:
        raise LogError(source, "velocity_enu",
                       f"expected a steady hover of >= {min_duration_s:g} s (|vz| <= {max_vz_m_s:g} m/s, "
                       f"|vxy| <= {max_vxy_m_s:g} m/s, |az| <= {max_az_m_s2:g} m/s^2), found none")
    motor_means = None
    if motors is not None and all(s.motors_mean is not None for s in segs):
        w = np.array([s.duration_s for s in segs])
        motor_means = np.average(np.array([s.motors_mean for s in segs]), axis=0, weights=w)
    hte_segs = None if hte is None else [float(np.nanmean(hte[(t >= s.t_start_s) & (t <= s.t_end_s)])) for s in segs]
    has_rpm = rpm is not None and all(s.rpm_mean is not None and np.all(s.rpm_mean > 0) for s in segs)
    return HoverFlight(source, t, v["throttle"][:, 0], v["velocity_enu"], hte, segs, hv.summarize_hover(segs),
                       motor_means, hte_segs, bool(has_rpm), log.params.get("MPC_THR_HOVER"),
                       "SITL" in str(log.info.get("ver_hw", "")))


def hover_parameters(flight: HoverFlight, vp: VehicleParams | None, mass_kg: float | None = None) -> HoverResult:
    """The rotor parameter a hover implies.

    With per-rotor RPM: ``kt = m g / sum(w_i^2)`` [N/(rad/s)^2], duration-weighted over
    the segments (``mass_kg`` [kg], else the params file's, is required).  Without RPM
    but with ``vp``: the parameter that makes ``vp`` hover at the measured command.
    """
    mass = mass_kg if mass_kg is not None else (vp.mass_kg if vp is not None else None)
    grav = vp.gravity_m_s2 if vp is not None else hv.GRAVITY_DEFAULT
    segs = flight.segments
    notes: list[str] = []
    if flight.rpm_logged:
        if mass is None:
            raise ParamsError("--mass-kg/--params", "vehicle.mass_kg",
                              "the log has rotor RPM; kt = m g / sum(w^2) needs the mass")
        kts = hv.kt_per_segment(segs, mass, grav)
        kt = float(np.average(kts, weights=np.array([s.duration_s for s in segs])))
        if flight.sitl:
            notes.append("SITL esc_status RPM is synthetic (control x 6000), so this kt is not physical")
        return HoverResult(flight, {"rotors": {"kt_n_s2_rad2": kt}}, notes,
                           kt={"value": kt, "per_segment": kts, "spread": float(np.std(kts)),
                               "mass_kg": mass, "gravity_m_s2": grav})
    if vp is not None:
        u_h = float(np.mean(flight.motor_means)) if flight.motor_means is not None else flight.summary.throttle_mean
        derived = hv.params_from_hover_command(vp, u_h)
        return HoverResult(flight, {"rotors": derived}, notes, params_source=vp.source,
                           derived={"hover_command": u_h, **derived, "thrust_model": vp.rotors.thrust_model})
    notes.append("no RPM and no --params: only the hover throttle is reported (no parameter-file key)")
    return HoverResult(flight, {}, notes)


# --------------------------------------------------------------------------- delay


def identify_delays(log: FlightLog, vp: VehicleParams | None, *, source: str | None = None,
                    pairs: Sequence[str] | None = None, mode: str = "level", highpass_s: float = 1.0,
                    n_boot: int = 300) -> DelayResult:
    """Delays of the :func:`delay_inputs` pairs over the longest airborne interval (1 s in from each end).

    ``pairs`` None: every pair the log has; named pairs it lacks are an error.
    ``mode``, ``highpass_s`` [s] (0: off; never for ``climb``) and ``n_boot`` go to
    :func:`.delay.estimate_delay`.  ``source`` names the log in messages and the report (default ``log.path``).
    """
    source = log.path if source is None else source
    check_flyable(log)
    notes: list[str] = []
    geometry: rg.RotorGeometry | None
    try:
        geometry, note = rotor_geometry(log, vp)
        if note:
            notes.append(note)
    except LogError as exc:
        geometry = None
        notes.append(f"no rotor geometry ({exc.expected}): motor_* pairs skipped")
    inputs = delay_inputs(log, geometry)
    iv = log.airborne_intervals()
    if not iv:
        raise LogError(source, "landed", "expected an airborne stretch (land detector), found none")
    a, b = max(iv, key=lambda x: x[1] - x[0])
    a, b = a + 1.0, b - 1.0
    ests = []
    for name in inputs if pairs is None else pairs:
        if name not in inputs:
            raise LogError(source, name, "expected the series this pair needs; not in this log")
        d = inputs[name]
        in_c = (d.t_cmd >= a) & (d.t_cmd <= b) & np.isfinite(d.cmd)
        in_r = (d.t_resp >= a) & (d.t_resp <= b) & np.isfinite(d.resp)
        try:
            e = estimate_delay(d.t_cmd[in_c], d.cmd[in_c], d.t_resp[in_r], d.resp[in_r], max_delay_s=d.max_delay_s,
                               min_delay_s=d.min_delay_s, mode=mode,
                               highpass_s=None if name == "climb" or not highpass_s else highpass_s,
                               n_boot=n_boot, label=f"{name}: {d.label}")
        except ValueError as exc:
            notes.append(f"{name}: {exc}")
            continue
        ests.append((name, e))
    if not ests:
        raise LogError(source, "delay pairs",
                       f"expected at least one usable command/response pair; {'; '.join(notes)}")
    return DelayResult(source, (a, b), mode, ests, notes)


# --------------------------------------------------------------------------- regress


def _longest_finite_run(ok: np.ndarray) -> np.ndarray | None:
    """Indices of the longest run of True in ``ok`` (filters need contiguous data), None if none."""
    runs = np.split(np.arange(ok.size), np.flatnonzero(np.diff(ok.astype(int)) != 0) + 1)
    runs = [r for r in runs if ok[r[0]]]
    return max(runs, key=len) if runs else None


#: default low-pass [Hz] of the equation-error regression: the band in which the gyro-derived angular
#: acceleration is clean, so the errors sit in the commands and the moment form is unbiased (PX4 SIH:
#: roll/pitch effectiveness within 5 % of truth at 2.5 Hz; at 8 Hz the differentiated gyro noise
#: biases it +40-80 %).  The same cut-off as the nominal built from a log (identify/nominal.py).
ROT_LOWPASS_HZ = 2.5


def identify_regression(log: FlightLog, vp: VehicleParams | None, *, source: str | None = None,
                        rate_hz: float = 50.0, lowpass_hz: float | None = None, tau_s: float = 0.05,
                        trim_s: float = 2.0, accel_source: str = "rates", intercept: bool = False,
                        rcond: float = 1e-3) -> RegressionResult:
    """Equation-error least squares of the translational and rotational dynamics over the airborne data.

    Rotor states come from the logged motor commands through the params file's lag
    and thrust model, else a lag ``tau_s`` [s] with thrust proportional to command.
    Samples are resampled to ``rate_hz`` [Hz], trimmed ``trim_s`` [s] after take-off and
    before touchdown, and both sides low-passed at ``lowpass_hz`` [Hz] (default
    ``ROT_LOWPASS_HZ``, at most 0.4 x the motor log rate).  The rotational coefficients come
    from the moment form (:func:`~twin_nodes.identify.regression.fit_moment_form`).  With ``vp``, ``kT`` and the inertias implied by its mass,
    arm length and km go to the block where the coefficients have |t| >= 20.
    ``source`` names the log in messages and the report (default ``log.path``).
    """
    source = log.path if source is None else source
    check_flyable(log)
    geometry, note = rotor_geometry(log, vp)
    notes = [note] if note else []
    mot = log.require("motors")
    if mot.values.shape[1] != geometry.count:
        raise LogError(source, "motors", f"expected {geometry.count} motors (geometry), got {mot.values.shape[1]}")
    # Rotor states at the log's own motor sample times (ZOH + exact lag), then resampled.
    if vp is not None:
        r = vp.rotors
        states = rg.rotor_states_from_commands(mot.t_s, mot.values, tau_up_s=r.tau_up_s, tau_down_s=r.tau_down_s,
                                               reference=r.reference_from_command)
        model, fac = r.thrust_model, r.thr_mdl_fac
        notes.append(f"rotor states from {vp.source}: {model}, tau_up {r.tau_up_s:g} s, tau_down {r.tau_down_s:g} s")
    else:
        states = rg.rotor_states_from_commands(mot.t_s, mot.values, tau_up_s=tau_s)
        model, fac = "command", 0.0
        notes.append(f"no --params: thrust taken proportional to the lagged motor command (tau {tau_s:g} s); "
                     "kT is thrust per unit command")
    tt_native = rg.thrust_regressor(states, model, fac)

    names = ["specific_force_flu", "velocity_enu", "attitude_q", "body_rates_flu"]
    for n in names:
        log.require(n)
    t, v = log.resample(names, rate_hz)
    tt = np.column_stack([np.interp(t, mot.t_s, tt_native[:, j], left=np.nan, right=np.nan)
                          for j in range(tt_native.shape[1])])
    ta, aa, aa_src = angular_accel(log, accel_source)
    acc = np.column_stack([np.interp(t, ta, aa[:, k], left=np.nan, right=np.nan) for k in range(3)])
    notes.append(f"angular acceleration: {aa_src}")
    vb = rg.world_to_body(v["attitude_q"], v["velocity_enu"])
    motor_rate = (len(mot) - 1) / (mot.t_s[-1] - mot.t_s[0])
    lp = lowpass_hz if lowpass_hz is not None else min(ROT_LOWPASS_HZ, 0.4 * motor_rate)
    notes.append(f"zero-phase low-pass {lp:g} Hz on both sides (motors logged at {motor_rate:.1f} Hz)")
    notes.append("rotational coefficients by the moment form (commanded moment regressed on the measured angular "
                 "acceleration and rates, mapped back): the logged commands carry the controller's noise, which "
                 "attenuates plain least squares of the acceleration on them (19-24 % low on PX4 SIH)")

    # Airborne stretches only (ground reaction is not in the model), each filtered on its own; samples
    # with a saturated motor, ground contact or a land-detector transition are left out (fit_mask)
    min_n = max(20, int(2 * rate_hz))
    sels = [sel for a, b in log.airborne_intervals()
            if (sel := np.flatnonzero((t >= a + trim_s) & (t <= b - trim_s))).size >= min_n]
    keep = np.ones(t.size, bool)
    if sels:
        air = np.concatenate(sels)
        left_out = fit_mask(log, t[air], rate_hz)
        keep[air] = left_out.keep
        notes.append(f"samples left out: {left_out.describe()}")
    segs = []
    for sel in sels:
        block_ = np.column_stack([v["specific_force_flu"][sel], vb[sel], v["body_rates_flu"][sel], acc[sel], tt[sel]])
        rr = _longest_finite_run(np.all(np.isfinite(block_), axis=1))
        if rr is None or rr.size < min_n:
            continue
        # the runs of it the fit may use (each filtered on its own)
        for part in np.split(rr, np.flatnonzero(np.diff(keep[sel[rr]].astype(int)) != 0) + 1):
            if keep[sel[part[0]]] and part.size >= min_n:
                segs.append((t[sel[part]], rg.lowpass(block_[part], rate_hz, lp)))
    if not segs:
        raise LogError(source, "landed", f"expected airborne data longer than 2 x {trim_s:g} s trim + 2 s")
    data = np.concatenate([s[1] for s in segs])
    d = RegressionData(np.concatenate([s[0] for s in segs]), data[:, 0:3], data[:, 3:6], data[:, 6:9],
                       data[:, 9:12], data[:, 12:])
    trans = rg.translational_regression(d.f, d.thrust, d.v_body, intercept=intercept, rcond=rcond)
    rot = rg.rotational_regression(d.w_dot, d.w, d.thrust, geometry, intercept=intercept, rcond=rcond)

    # Which coefficients the data determined (identifiable, |t| >= 3), and what that says about physics.
    identified = [nm for fits in (trans, rot) for fit in fits.values()
                  for nm, ok_, tv in zip(fit.names, fit.identifiable, fit.t_values)
                  if ok_ and abs(tv) >= 3.0 and not nm.startswith("bias")]
    nominal = None
    known: tuple[str, ...] = ()
    if vp is not None:
        I = vp.inertia
        nominal = {"m": vp.mass_kg, "l": geometry.arm_length_m, "km": vp.rotors.km_m,
                   "Ixx": I[0, 0], "Iyy": I[1, 1], "Izz": I[2, 2],
                   "kT": vp.rotors.kt_n_s2_rad2 if model == "omega_squared" else vp.rotors.thrust_max_n}
        known = ("m", "l", "km")
    struct_free = rg.structural_identifiability(identified, nominal)
    struct_known = rg.structural_identifiability(identified, nominal, known=known) if known else None

    block, implied = _implied_params(vp, geometry, model, trans, rot, notes) if vp is not None else ({}, {})
    return RegressionResult(source, rate_hz, lp, model, intercept, geometry, d, trans, rot, identified,
                            struct_free, struct_known, vp.source if vp is not None else "", implied, block, notes)


def _implied_params(vp: VehicleParams, geometry: rg.RotorGeometry, model: str, trans: dict[str, rg.LinearFit],
                    rot: dict[str, rg.LinearFit], notes: list[str]) -> tuple[dict, dict]:
    """(block, implied): ``kT`` from ``kT/m`` and the inertias [kg m^2] from the rotational
    coefficients, given ``vp``'s mass, arm length and km; appends to ``notes`` why nothing is written."""
    l = geometry.arm_length_m
    block: dict = {}
    implied: dict = {}

    def good(fit: rg.LinearFit, nm: str) -> bool:
        # Identifiable, positive and within 5 % (1 sigma); a low R2 with white
        # sensor noise still gives an unbiased, precise coefficient.
        i = fit.names.index(nm)
        return bool(fit.identifiable[i] and fit.coef[i] > 0 and abs(fit.t_values[i]) >= 20.0)

    tz = trans["z"]
    if "kT/m" in tz.names and good(tz, "kT/m"):
        kT = tz["kT/m"] * vp.mass_kg
        implied["kT"] = kT
        key = "kt_n_s2_rad2" if model == "omega_squared" else "thrust_max_n"
        block.setdefault("rotors", {})[key] = kT
        for ax, nm, ikey in (("roll", "kT*l/Ixx", "ixx_kg_m2"), ("pitch", "kT*l/Iyy", "iyy_kg_m2")):
            if good(rot[ax], nm):
                implied[ikey] = kT * l / rot[ax][nm]
        if good(rot["yaw"], "km*kT/Izz") and vp.rotors.km_m > 0:
            implied["izz_kg_m2"] = vp.rotors.km_m * kT / rot["yaw"]["km*kT/Izz"]
        inert = {k: implied[k] for k in ("ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2") if k in implied}
        if inert:
            block["vehicle"] = inert
    else:
        notes.append("kT/m not well determined (relative stderr > 5 % or <= 0): no parameter-file keys written")
    if block:
        try:
            check_merged(vp, block, "merged")
        except ParamsError as exc:
            notes.append(f"implied values rejected by the params schema ({exc}); not written")
            block = {}
    return block, implied


# --------------------------------------------------------------------------- noise


def identify_noise(log: FlightLog, vp: VehicleParams | None, *, source: str | None = None,
                   allow_armed: bool = False, min_duration_s: float = 3.0, gyro_std_max: float = 0.02,
                   accel_std_max: float = 0.15, accel_reference: str = "mean_direction") -> NoiseResult:
    """IMU bias, white noise and Allan deviation from the longest stationary landed stretch.

    Stationary: 1 s moving std of each gyro axis <= ``gyro_std_max`` [rad/s] and of the
    accelerometer magnitude <= ``accel_std_max`` [m/s^2], for >= ``min_duration_s`` [s].
    Disarmed samples only, unless none qualify and ``allow_armed``.
    ``accel_reference``: see :mod:`twin_nodes.identify.noise`.  ``source`` names the log in
    messages and the report (default ``log.path``).
    """
    source = log.path if source is None else source
    check_flyable(log, airborne=False, horizontal=False)  # the landed pre-arm stretch: no flight needed
    notes: list[str] = []
    gy = log.require("gyro_flu")
    sf = log.require("specific_force_flu")
    if len(gy) != len(sf):
        raise LogError(source, "sensor_combined",
                       f"expected as many accel as gyro samples, got {len(sf)} and {len(gy)}")
    t = gy.t_s
    landed = log.get("landed")
    armed = log.get("armed")
    if landed is None or armed is None:
        raise LogError(source, "vehicle_land_detected/vehicle_status",
                       "expected land detector and arming state to find the ground segment")
    is_landed = landed.at(t)[:, 0] > 0.5
    is_armed = armed.at(t)[:, 0] > 0.5
    g_all, a_all = gy.values, sf.values
    runs = nz.stationary_runs(t, g_all, a_all, min_duration_s=min_duration_s,
                              gyro_std_max=gyro_std_max, accel_std_max=accel_std_max)
    cand = []
    for want_armed in ((False, True) if allow_armed else (False,)):
        ok = is_landed & (is_armed == want_armed)
        for a, b in runs:
            sub = np.flatnonzero(ok[a:b]) + a
            if sub.size == 0:
                continue
            for pc in np.split(sub, np.flatnonzero(np.diff(sub) != 1) + 1):
                if t[pc[-1]] - t[pc[0]] >= min_duration_s:
                    cand.append((want_armed, pc))
        if cand:
            break
    if not cand:
        what = "landed (disarmed, or armed with --allow-armed)" if allow_armed else \
            "landed and disarmed (pre-arm ground segment)"
        raise LogError(source, "sensor_combined",
                       f"expected >= {min_duration_s:g} s stationary (1 s std of gyro <= {gyro_std_max:g} "
                       f"rad/s, of |accel| <= {accel_std_max:g} m/s^2), {what}; none found"
                       + ("" if allow_armed else " (logging may start at arming: try --allow-armed)"))
    used_armed, idx = max(cand, key=lambda c: c[1].size)
    if used_armed:
        notes.append("no disarmed ground segment: used landed+armed samples, so motor vibration is included")
    tt = t[idx]
    dt = np.diff(tt)
    rate = 1.0 / float(np.mean(dt))
    jitter = float(np.std(dt) / np.mean(dt))
    if jitter > 0.05:
        notes.append(f"sample interval jitter {jitter:.1%}: Allan deviation computed on sample index at the mean rate")
    notes.append("PX4 sensor_combined is low-pass filtered (IMU_GYRO_CUTOFF "
                 f"{log.params.get('IMU_GYRO_CUTOFF')} Hz) and decimated: white-noise std is of the filtered "
                 "signal; random walk from the Allan -1/2 slope is not affected by the filter")
    res = nz.imu_noise(g_all[idx], a_all[idx], rate,
                       gravity_m_s2=vp.gravity_m_s2 if vp is not None else nz.GRAVITY_DEFAULT,
                       accel_reference=accel_reference)
    for what, allan in (("gyro", res.gyro_allan), ("accel", res.accel_allan)):
        unb = [a for a, ok_ in zip("xyz", allan.bias_instability_bounded) if not ok_]
        if unb:
            notes.append(f"{what} Allan deviation still falling at the longest tau on axis {','.join(unb)}: "
                         "bias instability there is an upper bound")
    return NoiseResult(source, (float(tt[0]), float(tt[-1])), int(idx.size), rate, bool(used_armed), res,
                       {"sensors": nz.sensors_block(res)}, notes)
