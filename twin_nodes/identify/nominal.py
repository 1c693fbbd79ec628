"""A complete nominal twin of the vehicle that flew, built from its own PX4 log.

Nothing is silent: every value of the params file comes with its source (a log
parameter, identified on this flight with its standard error, a PX4 default, or an
assumption), and :func:`header` writes them into the file.

- rotor layout, spin, thrust curve (``THR_MDL_FAC``), controller gains and limits:
  the log's PX4 parameters (:mod:`twin_nodes.vehicle.px4_params`);
- maximum thrust per rotor ``T_max`` and linear drag: the specific-force equation
  ``f_z = (T_max/m) sum T~(s_i) - (k_z/m) v_z`` (body FLU, accelerometer) over the
  airborne part, ``T~ = f s^2 + (1 - f) s`` of the lagged commands ``s``; the thrust at the top of the
  command range (a motor >= 0.9, steady height, saturated samples included) checked against the map, or
  said not reached (:func:`_thrust_at_top`: a report, not applied);
- inertia and angular damping: the rotor moment computed from the commands (``T_max`` from
  above, the lever arms) regressed on the measured angular acceleration and rate,
  ``M = I w' + k_w w + trim``: the commands carry the controller's noise, so they stand on the
  side of the equation that tolerates it; yaw gives ``Izz / km`` only, so ``Izz`` rests on the
  assumed ``km``;
- static trims: the median motor outputs in steady flight give a centre-of-mass offset
  (roll/pitch) and a tangential rotor tilt (yaw); an offset beyond 30 % of the arm only where the
  flight's two halves show it held and it lies inside the rotor polygon (static_trims.com_verdict);
  the pack voltage, when it sags, a battery term;
- the motor time constant: the lag that best explains the roll/pitch accelerations
  (a scan over 0.02-0.25 s; reported with the range within 2 % of the best residual);
- mass: the user's ``--mass-kg``, else the airframe's typical mass (an assumption:
  every identified force and inertia scales with it, so the twin's motion does not).

Both sides of every regression are low-passed by the same zero-phase filter.
"""

from __future__ import annotations

import hashlib
import inspect
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twin_nodes.base.constants import G_STANDARD_M_S2
from twin_nodes.base.errors import LogError, ParamsError
from twin_nodes.identify.coaxial import ASSUMED as COAX_ASSUMED, LOWPASS_HZ as COAX_LOWPASS_HZ, coaxial_efficiency
from twin_nodes.identify.fit_mask import contact_mask, fit_mask
from twin_nodes.identify.regression import (RotorGeometry, fit_linear, lowpass,
                                           rotor_states_from_commands, thrust_regressor, translational_regression,
                                           world_to_body)
from twin_nodes.identify.rate_bound import gain_margin
from twin_nodes.identify.static_trims import ComSupport, Trims, com_verdict, model_trims
from twin_nodes.identify.yaw_gain import applied_yaw_gain, yaw_gain_for_twin
from twin_nodes.logs.flyable import MIN_HORIZONTAL_FRACTION, check_flyable, read_flight
from twin_nodes.logs.ulog_io import FlightLog
from twin_nodes.physics.core import NX_BODY
from twin_nodes.vehicle.params import VehicleParams, from_ros_dict
from twin_nodes.vehicle.px4_params import int_param  # noqa: I001 - a log integer, range-checked
from twin_nodes.vehicle.px4_params import (AIRFRAMES, RateGainsPx4, lower_rotors, outer_loop_gains, param,
                                           rate_gains_physical, rotor_layout)

#: assumed rotor torque / thrust ratio [m] (Q = km T): 0.016 (APC 10x4.7: C_P/(2 pi C_T) D) to 0.024
#: (Buho Negro's datasheet); PX4's CA_ROTORn_KM (0.05 by default) is an allocation value, not a measurement.
KM_ASSUMED_M = 0.02
TAU_SCAN_S = np.round(np.arange(0.02, 0.2501, 0.01), 3)
#: the lag counts as identified when the scan's near-best range is no wider than this [s]
TAU_SPREAD_MAX_S = 0.08
TAU_ASSUMED_S = 0.05
#: the twin's controller rate (ControllerGains.rate_hz; identify may not import twin, tests/test_layout.py)
TWIN_CONTROL_HZ = 250.0
GRID_HZ = 50.0
#: a steady wind below this [m/s] is not told apart from the estimate's floor: the PX4 SIH flights
#: (no wind) give 0.02-0.11 m/s
WIND_MIN_M_S = 0.3
#: the drag's line of action counts as above the centre of mass from this fraction of the arm: the
#: PX4 SIH flights (drag at the centre of mass) give |h| <= 2 mm (0.7 % of the arm)
DRAG_HEIGHT_MIN = 0.05
RATES = "body_rates_flu"


@dataclass
class Nominal:
    """The params built from a log and where each value came from."""

    params: VehicleParams
    log_path: str
    sources: dict[str, str]
    fits: dict[str, float] = field(default_factory=dict)

    def header(self) -> str:
        """Comment block for the params file: one line per value and its source."""
        lines = [f"Nominal twin built from {self.log_path} by 'rotortwin params from-ulog'.",
                 "Every value and its source:"]
        lines += [f"  {k}: {v}" for k, v in self.sources.items()]
        return "\n".join(lines)


def _airborne_grid(log: FlightLog, rate_hz: float, trim_s: float = 2.0) -> np.ndarray:
    """Uniform times inside the airborne intervals, ``trim_s`` away from take-off and touchdown."""
    pieces = []
    for a, b in log.airborne_intervals():
        if b - a > 2 * trim_s + 2.0:
            pieces.append(np.arange(a + trim_s, b - trim_s, 1.0 / rate_hz))
    if not pieces:
        raise LogError(log.path, "landed",
                       "too short to identify: expected at least one airborne interval longer than 6 s")
    return np.concatenate(pieces)


def _mass(log: FlightLog, mass_kg: float | None) -> tuple[float, str]:
    if mass_kg is not None:
        return float(mass_kg), "--mass-kg"
    autostart = int_param(log.params, "SYS_AUTOSTART", log.path, 0, 99_999_999)
    af = AIRFRAMES.get(autostart)
    if af is not None:
        return af.mass_kg, (f"ASSUMED typical take-off mass of airframe {autostart} ({af.name}); give --mass-kg "
                            f"(forces and inertia scale with it, the twin's motion does not)")
    return 1.5, "ASSUMED 1.5 kg (unknown airframe); give --mass-kg (forces and inertia scale with it)"


def _signals(log: FlightLog, t: np.ndarray) -> dict[str, np.ndarray]:
    return {
        "motors": log.require("motors").at(t),
        "rates": log.require(RATES).at(t),
        "q": log.require("attitude_q").at(t),
        "v_enu": log.require("velocity_enu").at(t),
        "f_body": log.require("specific_force_flu").at(t),
    }


def _segments(t: np.ndarray, rate_hz: float) -> list[slice]:
    """Contiguous runs of the (possibly gapped) grid."""
    cut = np.flatnonzero(np.diff(t) > 1.5 / rate_hz) + 1
    bounds = np.concatenate([[0], cut, [t.size]])
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b - a > 20]


def _per_segment(fn, t: np.ndarray, x: np.ndarray, segs: list[slice]) -> np.ndarray:
    out = np.empty_like(np.asarray(x, float))
    for s in segs:
        out[s] = fn(t[s], x[s])
    return out


def nominal_from_log(log: FlightLog, *, mass_kg: float | None = None, arm_m: float | None = None,
                     name: str | None = None, cutoff_hz: float = 2.5) -> Nominal:
    """Build the nominal params of the vehicle that flew ``log`` (see the module docstring).  A log that
    is no usable flight (too short, never airborne, without GPS or horizontal velocity) is refused in one
    line (:func:`twin_nodes.logs.flyable.check_flyable`)."""
    p = log.params
    src: dict[str, str] = {}
    layout = rotor_layout(p, log.path, arm_m, log.moving_outputs)
    n = len(layout.x_flu_m)
    if log.n_motors != n:
        raise LogError(log.path, "actuator_motors",
                       f"{n} rotors in the parameters, {log.n_motors} motor outputs in the log")
    check_flyable(log, horizontal=False)
    src["rotors.x_flu_m/y_flu_m/z_flu_m, direction"] = layout.source
    m, src["vehicle.mass_kg"] = _mass(log, mass_kg)
    f_fac, src["rotors.thr_mdl_fac"] = param(p, "THR_MDL_FAC", 0.0)
    f_fac = min(max(f_fac, 0.0), 1.0)

    t = _airborne_grid(log, GRID_HZ)
    sig = _signals(log, t)
    t_air, sig_air = t, dict(sig)
    # a flight without horizontal velocity (no GPS: PX4 logs it NaN) is identified on what it has:
    # the vertical and rotational equations with the horizontal velocity taken as 0, and no horizontal
    # drag, wind or drag height (their regressors are the horizontal velocity)
    no_horizontal = float(np.mean(np.isfinite(sig["v_enu"][:, :2]).all(axis=1))) < MIN_HORIZONTAL_FRACTION
    if no_horizontal:
        sig["v_enu"] = sig["v_enu"].copy()
        sig["v_enu"][:, :2] = 0.0
    # every equation below needs all of these at a sample: a stretch where one is unknown (PX4 logs NaN
    # velocity while its horizontal estimate is invalid) is left out, else the low-pass would spread the
    # NaN over its whole segment and leave no sample to fit
    ok = np.ones(len(t), bool)
    for key in ("motors", "rates", "q", "v_enu", "f_body"):
        ok &= np.all(np.isfinite(np.asarray(sig[key], float).reshape(len(t), -1)), axis=1)
    # nor do they hold with a motor at its bound, on the ground or while the land detector changes its mind
    left_out = fit_mask(log, t, GRID_HZ)
    src["identification: samples left out"] = left_out.describe()
    ok &= left_out.keep
    t = t[ok]
    sig = {k: v[ok] for k, v in sig.items()}
    segs = _segments(t, GRID_HZ)
    if not segs:
        raise LogError(log.path, "motors", "expected airborne motor outputs with body rates, found none")
    # only samples inside a segment go on: the per-segment filters leave the rest undefined (np.empty)
    inside = np.concatenate([np.arange(sg.start, sg.stop) for sg in segs])
    if inside.size < t.size:
        t = t[inside]
        sig = {k: v[inside] for k, v in sig.items()}
        segs = _segments(t, GRID_HZ)

    def lp(x: np.ndarray) -> np.ndarray:
        return _per_segment(lambda _t, v: lowpass(v, GRID_HZ, cutoff_hz), t, x, segs)

    # central difference, then the same low-pass as the regressors: a smoothing derivative
    # would filter one side of the equation only and bias the inertia up
    alpha = lp(_per_segment(lambda tt, w: np.gradient(w, tt, axis=0), t, sig["rates"], segs))
    rates_lp = lp(sig["rates"])
    geom = RotorGeometry(np.array(layout.x_flu_m), np.array(layout.y_flu_m), np.array(layout.direction, float))

    def thrust_units(tau: float) -> np.ndarray:
        s = np.empty_like(sig["motors"])
        for sg in segs:
            s[sg] = rotor_states_from_commands(t[sg], sig["motors"][sg], tau_up_s=tau)
        return lp(thrust_regressor(s, "thrust_factor", f_fac))

    # --- motor time constant: the lag that best explains roll and pitch accelerations, with the thrust
    # units weighted by each rotor's thrust per command (coaxial pairs: the lower rotor's efficiency)
    lag_scan: dict = {}

    def scan_lag(w: np.ndarray) -> tuple[float, str]:
        cost = []
        for tau_k in TAU_SCAN_S:
            fits = _moment_fits(alpha, rates_lp, thrust_units(float(tau_k)) * w, geom, 1.0, 1.0)
            cost.append(sum(1.0 - fits[ax].r2 for ax in ("roll", "pitch")))
        cost = np.asarray(cost)
        i_best = int(np.argmin(cost))
        near = TAU_SCAN_S[cost <= cost[i_best] * 1.02]
        at_edge = i_best in (0, len(TAU_SCAN_S) - 1)
        lag_scan.update(near=near, at_edge=at_edge)
        if near.max() - near.min() <= TAU_SPREAD_MAX_S and not at_edge:
            tau_b = float(TAU_SCAN_S[i_best])
            return tau_b, (f"identified: lag explaining roll/pitch acceleration best, {tau_b:.3f} s "
                           f"(within 2 % of the best residual: {near.min():.2f}-{near.max():.2f} s)")
        why = (f"its best fit sits at the edge of the {TAU_SCAN_S[0]}-{TAU_SCAN_S[-1]} s scan" if at_edge else
               f"residual within 2 % of its best from {near.min():.2f} to {near.max():.2f} s")
        return TAU_ASSUMED_S, (f"ASSUMED {TAU_ASSUMED_S} s (typical motor + ESC): the flight does not determine "
                               f"it at this log's motor rate ({why})")

    # coaxial pairs: the lower rotors' thrust per command relative to the upper ones, identified on the
    # body-z specific force (coaxial.py) or ASSUMED; the lag is scanned with it (again once it is
    # identified), and from here on the thrust units carry it, so T_max below is an upper rotor's
    lower, lower_how = lower_rotors(layout) if layout.coaxial else ((), "")
    w_rot = np.ones(n)
    w_rot[list(lower)] = COAX_ASSUMED
    tau, src["rotors.tau_up_s/tau_down_s"] = scan_lag(w_rot)
    v_body = lp(world_to_body(sig["q"], sig["v_enu"]))
    coax = None
    if lower:
        def slow(x: np.ndarray) -> np.ndarray:
            return _per_segment(lambda _t, v: lowpass(v, GRID_HZ, COAX_LOWPASS_HZ), t, x, segs)

        def fit_coax():
            return coaxial_efficiency(slow(thrust_units(tau)), slow(lp(sig["f_body"])[:, 2]), slow(v_body[:, 2]),
                                      lower)
        coax = fit_coax()
        if coax.identified and abs(coax.efficiency - COAX_ASSUMED) > 0.01:
            w_rot[list(lower)] = coax.efficiency
            tau, src["rotors.tau_up_s/tau_down_s"] = scan_lag(w_rot)
            coax = fit_coax()
        w_rot[list(lower)] = coax.efficiency
    tt = thrust_units(tau) * w_rot

    # --- thrust and drag from the specific force
    trans = translational_regression(lp(sig["f_body"]), tt, v_body)
    kt_m, kt_m_se = trans["z"]["kT/m"], trans["z"].se("kT/m")
    if not kt_m > 0:
        raise LogError(log.path, "specific_force_flu", "expected the thrust to carry the weight (fit kT/m > 0)")
    # battery sag: thrust at a given command falls with the pack voltage, T = T_max (V/V_ref)^e T~;
    # linearised, f_z = (T_max/m) sum T~ + (T_max e / m) sum T~ ln(V/V_ref) - (k_z/m) v_z
    battery = _battery_sag(log, t, tt, lp, v_body, sig, segs)
    if battery is not None:
        kt_m, kt_m_se, v_ref, expo, expo_se = battery
        src["effects.battery_sag"] = (f"identified: thrust ~ (V/{v_ref:.2f} V)^{expo:.2f} ± {expo_se:.2f} "
                                      f"(specific force z vs pack voltage)")
    else:
        src["effects.battery_sag"] = "not included: no voltage trace, too little sag, or no significant effect"
    t_max = m * kt_m
    src["rotors.thrust_max_n"] = (f"identified: {t_max:.3f} N ± {m * kt_m_se:.3f} (specific force z, mass above"
                                  + (f", at {battery[2]:.2f} V)" if battery is not None else ")"))
    src["rotors.thrust at the top of the command range"], top_fits = _thrust_at_top(
        log, t_air, sig_air, m, t_max * w_rot, f_fac, battery, cutoff_hz, tau)
    # isotropic horizontal drag: body x and y stacked with one shared coefficient (a mission
    # flown nose-first excites body x only), a trim offset per axis, and a steady wind: the drag
    # acts on the air-relative velocity, f_b = -(k/m) R^T (v - w) + bias; while the heading turns,
    # the world-fixed wind w separates from the body-fixed biases (linear in (k/m) w)
    f_lp = lp(sig["f_body"])
    if no_horizontal:
        drag, drag_se, wind, east_b, north_b = 0.0, 1.0, None, None, None
        src["effects.wind"] = "not included: the log has no horizontal velocity (no GPS)"
    else:
        drag, drag_se, wind, east_b, north_b = _horizontal_drag(t, sig, lp, f_lp, v_body, m, src)
    use_drag = drag > 3 * drag_se
    if wind is not None and not use_drag:
        wind = None
        src["effects.wind"] = "not included: the drag it acts through is not significant"
    # air-relative body velocity
    v_air = v_body.copy()
    if wind is not None:
        v_air[:, :2] -= wind[0] * east_b[:, :2] + wind[1] * north_b[:, :2]

    # --- inertia and damping from the rotational equations, as moment = I alpha + k_w w + trim:
    # the moment is computed from the commands, which carry the controller's noise (no response
    # follows it), so the commands go on the left; regressing alpha on the commands instead
    # attenuates the effectiveness and inflated the inertia 1.5-3x on PX4 SIH flights.
    km = KM_ASSUMED_M
    rot = _moment_fits(alpha, rates_lp, tt, geom, t_max, km)
    l = geom.arm_length_m
    inertia, damp, notes = [], [], []
    for ax in ("roll", "pitch", "yaw"):
        f = rot[ax]
        inertia.append(f["I"] if f["I"] > 0 else math.inf)
        damp.append(f["k_w"])
        notes.append(f"{f['I']:.4g} ± {f.se('I'):.2g}")
    # A rigid frame cannot exceed all its mass at the rotor radius: I <= 0.6 m l^2 (a quad X with
    # every gram at the rotors has 0.5 m l^2).  Beyond that bound, or below 0.05 m l^2, the
    # value is replaced by a shape prior: 0.2 m l^2 about roll and pitch (typical of 0.5-6 kg
    # quads: F450 0.12, X500 0.18, Iris 0.31) and Izz = Ixx + Iyy (flat frame).
    ml2 = m * l * l
    prior = (0.2 * ml2, 0.2 * ml2, 0.4 * ml2)
    for j, (key, what, lo, hi) in enumerate((("vehicle.ixx_kg_m2", "roll", 0.05, 0.6),
                                             ("vehicle.iyy_kg_m2", "pitch", 0.05, 0.6),
                                             ("vehicle.izz_kg_m2", "yaw", 0.1, 1.2))):
        extra = ", with km ASSUMED below" if j == 2 else ""
        if math.isfinite(inertia[j]) and lo * ml2 <= inertia[j] <= hi * ml2:
            src[key] = f"identified: {notes[j]} ({what} moment from the commands vs angular acceleration{extra})"
        else:
            src[key] = (f"ASSUMED shape prior {prior[j]:.4g} kg m^2 ({prior[j] / ml2:.1f} m l^2): the {what} fit "
                        f"({notes[j]}{extra}) is outside the rigid-frame range {lo}-{hi} m l^2")
            inertia[j] = prior[j]
            damp[j] = 0.0
    src["rotors.km_m"] = f"ASSUMED {km} m (typical propeller torque/thrust ratio; not identifiable with Izz)"
    # --- where the horizontal drag acts: at a height h above the centre of mass (the rotor H-force
    # acts at the hubs) it adds the moment h x F_drag, which the commands balance:
    # roll  M_x = I_x w'_x + k_w w_x + trim_x - h k v_air,y;  pitch  M_y = ... + h k v_air,x
    drag_h, drag_h_note = None, "no significant horizontal drag"
    if use_drag:
        drag_h, drag_h_note = _drag_height(alpha, rates_lp, tt, geom, t_max, v_air, drag, l)
    k_w = float(np.mean(damp[:2]))
    use_damp = k_w > 0 and all(rot[ax].t_values[1] > 3 for ax in ("roll", "pitch"))

    effects = {"enabled": []}
    if battery is not None:
        effects["enabled"].append("battery_sag")
        effects["battery_sag"] = {"v_ref": battery[2], "exponent": battery[3]}
    z_hub = list(layout.z_flu_m)
    # the vertical drag (the axial inflow lowers the thrust in a climb: along the thrust, no moment),
    # from the body-z equation with a drag quadratic in the climb rate, as the body_drag effect has it
    vz = v_body[:, 2]
    zfit = fit_linear(np.column_stack([tt.sum(axis=1), -np.abs(vz) * vz]), lp(sig["f_body"])[:, 2],
                      ["kT/m", "c_dz/m"])
    c_dz = m * zfit["c_dz/m"] if zfit["c_dz/m"] > 3 * zfit.se("c_dz/m") else 0.0
    if use_drag and drag_h is not None:
        # the horizontal drag as the in-plane rotor H-force, -k_d |omega_i| (hub air speed), at the hubs
        # at the identified height; k_d gives the identified drag at hover
        w_hover = 1000.0 * math.sqrt(min(m * G_STANDARD_M_S2 / (float(w_rot.sum()) * t_max), 1.0))
        k_d = drag / (n * w_hover)
        effects["enabled"].append("rotor_drag")
        effects["rotor_drag"] = {"k_d": k_d}
        z_hub = [drag_h] * n
        src["effects.rotor_drag"] = (f"identified: the horizontal drag {drag:.3f} N/(m/s) as the rotors' H-force at "
                                     f"the hubs (k_d {k_d:.3g} N/((rad/s)(m/s)) at hover); {drag_h_note}")
        src["rotors.z_flu_m"] = (f"identified: {drag_h * 1000:.0f} mm, the height of the drag's line of action "
                                 f"above the centre of mass (hub height and blade flapping together)")
        if c_dz > 0:
            effects["enabled"].append("body_drag")
            effects["body_drag"] = {"c_dx": 0.0, "c_dy": 0.0, "c_dz": c_dz}
            src["effects.body_drag"] = (f"identified: vertical drag c_dz {c_dz:.3f} ± {m * zfit.se('c_dz/m'):.3f} "
                                        f"N/(m/s)^2 (body z specific force vs |v_z| v_z)")
        else:
            src["effects.body_drag"] = "not included: no significant vertical drag"
    elif use_drag:
        effects["enabled"].append("linear_drag")
        effects["linear_drag"] = {"k_n_s_m": drag}
        src["effects.linear_drag"] = (f"identified: {drag:.3f} N/(m/s) (body x/y specific force vs air speed), at the "
                                      f"centre of mass: {drag_h_note}")
    if wind is not None:
        effects["enabled"].append("wind")
        effects["wind"] = {"vx": wind[0], "vy": wind[1], "gust_std": 0.0}
        src["effects.wind"] = (f"identified: steady wind {wind[0]:+.2f} m/s east, {wind[1]:+.2f} m/s north "
                               f"(± {wind[2]:.2f}; horizontal specific force vs the turning heading)")
    if not use_drag:
        src["effects.linear_drag"] = f"not included: horizontal drag fit {drag:.3g} N/(m/s) not significant"
    if use_damp:
        effects["enabled"].append("angular_damping")
        effects["angular_damping"] = {"k_nm_s_rad": k_w}
        src["effects.angular_damping"] = f"identified: {k_w:.4g} N m/(rad/s) (roll/pitch rate damping)"
    else:
        src["effects.angular_damping"] = f"not included: roll/pitch damping fit {k_w:.3g} not significant"

    if coax is not None:
        effects["enabled"].append("coaxial")
        effects["coaxial"] = {"efficiency": float(coax.efficiency), "lower_mask": float(sum(1 << i for i in lower))}
        src["effects.coaxial"] = f"{coax.source}; lower rotors (motors) {[i + 1 for i in lower]} {lower_how}"
        src["rotors.thrust_max_n"] += f"; an upper rotor's (the lower ones x {coax.efficiency:.3g})"

    # --- static trims: the mean rotor moments the controller holds in steady flight balance a
    # centre-of-mass offset (roll/pitch) and tangentially tilted rotors (yaw)
    steady = np.linalg.norm(sig["v_enu"], axis=1) < STEADY_SPEED_M_S
    if steady.sum() < STEADY_MIN_S * GRID_HZ:
        steady = np.ones(t.size, bool)
    # the roll/pitch balance holds on samples with a motor at a bound too (PX4 gives yaw up first, and a
    # vehicle that does not tumble holds its roll/pitch moments on average): a payload far off-centre keeps a
    # motor near a bound all flight, and these are then its only steady samples
    steady_s = float(steady.sum()) / GRID_HZ
    dx, dy, lever = _median_trims(t_max * tt[steady], layout, km, drag_h, drag, v_air[steady])
    _put_trims(effects, src, dx, dy, lever, l, "the roll/pitch trim of the median motor outputs in steady flight",
               "the yaw trim of the median motor outputs", lower_bounds=True,
               support=_com_support(layout, steady_s, [_median_trims(t_max * tt[h], layout, km, drag_h, drag, v_air[h])
                                                       for h in _halves(steady)]))

    # --- the log's own controller
    hover_cmd = _hover_command(t_max * float(w_rot.sum()), m, f_fac)
    gains, gsrc = outer_loop_gains(p, hover_cmd)
    # the yaw attitude gain the firmware applied (a fork may not divide MC_YAW_P by MC_YAW_WEIGHT)
    k_yaw, src["controller.yaw_p_1_s"] = yaw_gain_for_twin(applied_yaw_gain(log), gains["yaw_p_1_s"],
                                                          gains["yaw_weight"])
    if k_yaw is not None:
        gains["yaw_p_1_s"] = k_yaw
    slope = t_max * float(w_rot.mean()) * (2 * f_fac * hover_cmd + (1 - f_fac))
    rate = rate_gains_physical(RateGainsPx4.from_params(p), np.array(layout.x_flu_m), np.array(layout.y_flu_m),
                               np.array(layout.direction), float(abs(p.get("CA_ROTOR0_KM", 0.05)) or 0.05),
                               slope, tuple(inertia), km_physical_m=km)
    src["controller (outer loops)"] = "; ".join(sorted({s for s in gsrc.values()}))
    src["controller (rate loop)"] = ("log parameters MC_*RATE_P/I/D/K and the integrators' limits MC_*R_INT_LIM "
                                     "(each axis its own) converted from PX4's normalised torque to rad/s^2 with "
                                     "PX4's allocation scaling, the thrust slope and the inertia")
    # The converted loop gain is PX4's only if the inertia is the real one; where it is a prior the
    # conversion can exceed what the identified motor lag holds (phase margin ~55 deg needs
    # Kp tau <= 0.7, as ControllerGains.auto_defaults), so it is capped there and said so.
    # Where the lag is ASSUMED the cap stands on no measured lag; lifting it there (PX4's gains kept, the
    # twin's discrete loop holds them) was measured and not adopted (docs/identify_results.md): the
    # header says which lag it is and what margin PX4's own gains would keep in the twin's rate loop.
    lag_is = "ASSUMED" if src["rotors.tau_up_s/tau_down_s"].startswith("ASSUMED") else "identified"
    for key, limit in (("rate_p_1_s", 0.7 / tau), ("yawrate_p_1_s", 0.3 / tau)):
        if rate[key] > limit:
            scale = limit / rate[key]
            held = ""
            if key == "rate_p_1_s":
                margin = gain_margin(rate["rate_p_1_s"], rate["rate_i_1_s2"], rate["rate_d"], tau,
                                     1.0 / TWIN_CONTROL_HZ)
                held = f"; PX4's gains would keep a gain margin of {margin:.2g} in the twin's rate loop"
            src["controller (rate loop)"] += (f"; {key} {rate[key]:.3g} capped at {limit:.3g} ({'0.7' if key[0] == 'r' else '0.3'}"
                                             f"/tau for the {lag_is} lag{held}), its I/D scaled alike")
            for k in ((key, "rate_i_1_s2", "rate_d") if key == "rate_p_1_s" else (key, "yawrate_i_1_s2")):
                rate[k] *= scale
    gains.update(rate)
    # the attitude loops must stay slower than the rate loops they drive (cascade separation >= 2,
    # as ControllerGains.auto_defaults); PX4's own values are kept wherever that holds
    for att, inner in (("roll_p_1_s", "rate_p_1_s"), ("pitch_p_1_s", "rate_p_1_s"), ("yaw_p_1_s", "yawrate_p_1_s")):
        if gains[att] > gains[inner] / 2.0:
            src["controller (rate loop)"] += (f"; {att} {gains[att]:.3g} capped at {gains[inner] / 2.0:.3g} "
                                             f"(half the {inner.split('_')[0]} rate loop)")
            gains[att] = gains[inner] / 2.0

    rotors = {
        "x_flu_m": list(layout.x_flu_m), "y_flu_m": list(layout.y_flu_m), "z_flu_m": z_hub,
        "direction": list(layout.direction), "thrust_model": "thrust_factor", "thrust_max_n": float(t_max),
        "thr_mdl_fac": float(f_fac), "km_m": km, "tau_up_s": tau, "tau_down_s": tau,
        "omega_max_rad_s": 1000.0,
    }
    src["rotors.omega_max_rad_s"] = "nominal 1000 rad/s: only scales the reported rotor speed (no RPM in the log)"
    vname = name or f"from_ulog_{log.path.rsplit('/', 1)[-1].rsplit('.', 1)[0]}"
    data = {"vehicle": {"name": vname, "mass_kg": m, "ixx_kg_m2": inertia[0], "iyy_kg_m2": inertia[1],
                        "izz_kg_m2": inertia[2], "ixy_kg_m2": 0.0, "ixz_kg_m2": 0.0, "iyz_kg_m2": 0.0,
                        "gravity_m_s2": G_STANDARD_M_S2},
            "rotors": rotors, "effects": effects, "controller": gains, "simulation": {"dt_s": 0.002}}
    fits = {"tau_s": tau, "kT/m": kt_m, "kT/m_se": kt_m_se, "hover_command": hover_cmd,
            "drag_n_s_m": drag, "angular_damping": k_w, "roll_r2": rot["roll"].r2, "pitch_r2": rot["pitch"].r2,
            "yaw_r2": rot["yaw"].r2, "z_r2": trans["z"].r2, **top_fits}
    try:
        vp = from_ros_dict(data, log.path)
        # the trims again, now from the whole model's steady moments (rotor drag, wind, coaxial...):
        # what the twin itself needs to hold the vehicle's motor split (static_trims.py)
        held = _balanced(steady, sig["motors"], GRID_HZ)
        if held is not None:
            states = _model_states(log, vp, t, sig, segs, tau, rates_lp)[held]
            bv = log.get("battery_v") if battery is not None else None
            v_held = None if bv is None else bv.at(t[held]).reshape(-1)
            trims = model_trims(vp, states, alpha[held], v_held)
            parts = [model_trims(vp, states[h], alpha[held][h], None if v_held is None else v_held[h])
                     for h in _halves(np.ones(int(held.sum()), bool))]
            dx, dy, lever = _set_trims(effects, src, trims, l,
                                       _com_support(layout, float(held.sum()) / GRID_HZ,
                                                    [(q.dx, q.dy, q.lever) for q in parts]))
            vp = from_ros_dict(data, log.path)
        else:
            why = (f"; not made from the whole model: less than {BALANCED_MIN_S:g} s of steady flight with every motor "
                   f"inside its range (PX4 gives yaw up first at a bound)")
            for k in ("effects.com_offset", "effects.rotor_tilt"):
                src[k] += why
    except ParamsError as exc:  # e.g. rotors that cannot lift the assumed mass: the fits stay readable
        fits.update(_vehicle_fits(rot, t_max, km, m, drag_se, lag_scan["near"], lag_scan["at_edge"], battery, dx, dy,
                                  lever, tt[steady]))
        exc.fits = fits
        raise
    fits.update(_vehicle_fits(rot, t_max, km, m, drag_se, lag_scan["near"], lag_scan["at_edge"], battery, dx, dy, lever,
                              tt[steady]))
    for k in ("BAT1_N_CELLS", "BAT1_V_CHARGED", "BAT1_V_EMPTY", "IMU_GYRO_CUTOFF", "IMU_DGYRO_CUTOFF"):
        if k in p:
            src[f"log {k}"] = f"{p[k]:g} (recorded, not modelled)"
    return Nominal(vp, log.path, src, fits)


def _model_states(log: FlightLog, vp: VehicleParams, t: np.ndarray, sig: dict, segs: list[slice], tau: float,
                  rates: np.ndarray) -> np.ndarray:
    """The model's state along the fitted grid: the logged position, velocity and attitude, the (low-passed)
    body rates and the rotor states the logged commands give through the identified lag."""
    X = np.zeros((t.size, NX_BODY + vp.rotors.count))
    pos = log.get("position_enu")
    if pos is not None and len(pos):
        X[:, 0:3] = np.nan_to_num(pos.at(t))
    X[:, 3:6] = np.nan_to_num(sig["v_enu"])
    X[:, 6:10] = sig["q"]
    X[:, 10:13] = rates
    for sg in segs:
        X[sg, NX_BODY:] = rotor_states_from_commands(t[sg], sig["motors"][sg], tau_up_s=tau)
    return X


#: the static trims are made from the whole model only with this much steady flight in which PX4 held every
#: axis (as the fit mask's 6 s); with less, the median motor outputs give them as before
BALANCED_MIN_S = 6.0
#: steady flight for the static trims: below this ground speed [m/s], where at least ``STEADY_MIN_S`` of it
#: is left (else every sample); the refit's trims (discovery.stages.retrim) are read on the same samples
STEADY_SPEED_M_S = 2.0
STEADY_MIN_S = 10.0


def _com_support(layout, seconds: float, halves: list) -> ComSupport:
    return ComSupport(tuple(layout.x_flu_m), tuple(layout.y_flu_m), float(seconds),
                      tuple(tuple(float(v) for v in h) for h in halves))


def _halves(mask: np.ndarray) -> list[np.ndarray]:
    """The first and the second half (in time) of the samples ``mask`` selects, as two masks."""
    idx = np.flatnonzero(mask)
    out = []
    for part in (idx[: idx.size // 2], idx[idx.size // 2:]):
        h = np.zeros(mask.size, bool)
        h[part] = True
        out.append(h)
    return out


def _median_trims(thrust: np.ndarray, layout, km: float, drag_h, drag: float, v_air: np.ndarray
                  ) -> tuple[float, float, float]:
    """(dx, dy, lever) that balance the moments of the median rotor thrusts ``thrust`` (T, N) [N], less the
    drag moment at the median air speed where the drag acts at a height ``drag_h``."""
    med = np.median(thrust, axis=0) if len(thrust) else np.full(len(layout.x_flu_m), np.nan)
    total = float(med.sum())
    mx = float(np.dot(layout.y_flu_m, med))
    my = float(-np.dot(layout.x_flu_m, med))
    if drag_h is not None and len(v_air):
        mx += drag_h * drag * float(np.median(v_air[:, 1]))
        my -= drag_h * drag * float(np.median(v_air[:, 0]))
    mz = float(-km * np.dot(layout.direction, med))
    return -my / total, mx / total, -mz / total


def _put_trims(effects: dict, src: dict, dx: float, dy: float, lever: float, arm: float, how_com: str,
               how_tilt: str, lower_bounds: bool, support: ComSupport | None = None) -> None:
    """``com_offset`` (dx, dy) and ``rotor_tilt`` (lever) into ``effects`` where the centre of mass passes
    :func:`~twin_nodes.identify.static_trims.com_verdict` (within 30 % of the arm, or beyond it where
    ``support`` shows it held; inside the rotor polygon) and the lever a 10 deg tilt (``lower_bounds``: and
    above 1 % of the arm, 0.2 % for the lever); why in ``src``."""
    com_ok, com_why = com_verdict(dx, dy, arm, support, BALANCED_MIN_S)
    if com_ok and lower_bounds and not math.hypot(dx, dy) > 0.01 * arm:
        com_ok, com_why = False, "below 1 % of the arm"
    tilt_ok = abs(lever) <= arm * math.sin(math.radians(10.0)) and (not lower_bounds or abs(lever) > 0.002 * arm)
    if com_ok:
        effects["enabled"].append("com_offset")
        effects["com_offset"] = {"dx": dx, "dy": dy}
        src["effects.com_offset"] = f"identified: dx {dx * 1000:.1f} mm, dy {dy * 1000:.1f} mm ({how_com}){com_why}"
    else:
        src["effects.com_offset"] = f"not included: trim offset ({dx:.3g}, {dy:.3g}) m {com_why}"
    if tilt_ok:
        effects["enabled"].append("rotor_tilt")
        effects["rotor_tilt"] = {"lever_m": lever}
        src["effects.rotor_tilt"] = (f"identified: {lever * 1000:.2f} mm yaw lever = "
                                     f"{math.degrees(math.asin(lever / arm)):.2f} deg tangential tilt ({how_tilt}; km ASSUMED)")
    else:
        src["effects.rotor_tilt"] = (f"not included: yaw trim lever {lever:.3g} m "
                                     f"{'negligible or ' if lower_bounds else ''}beyond a 10 deg tilt")


def _balanced(steady: np.ndarray, motors: np.ndarray, rate_hz: float) -> np.ndarray | None:
    """The steady samples where PX4 held every axis: no motor within 1 % of a bound (where one is, the
    allocation gives up yaw first and the vehicle turns instead of balancing its moments); None where less
    than ``BALANCED_MIN_S`` of them is left (a flight at its motors' limits: no steady balance to read)."""
    m = np.asarray(motors, float)
    ok = steady & np.all((m > 0.01) & (m < 0.99), axis=1)
    return ok if ok.sum() >= BALANCED_MIN_S * rate_hz else None


def _set_trims(effects: dict, src: dict, trims: Trims, arm: float, support: ComSupport | None = None
               ) -> tuple[float, float, float]:
    """Put ``trims`` into ``effects`` (replacing the motor-output estimate) where they pass the same
    bounds; their sources in ``src``.  Returns (dx, dy, lever)."""
    dx, dy, lever = trims.dx, trims.dy, trims.lever
    other = ", ".join(f"{1000 * v:+.1f}" for v in trims.moment_other_nm)
    how = (f"the trim that balances, at the median of {trims.n_samples} steady samples with every motor inside its "
           f"range, the model's own moments "
           f"with the logged commands and state less the measured motion's (the rest of the model: ({other}) mN m)")
    for name in ("com_offset", "rotor_tilt"):
        effects.pop(name, None)
        if name in effects["enabled"]:
            effects["enabled"].remove(name)
    # no lower bound: a yaw lever of 0.05 % of the arm is a 1 % motor split with km 0.02 m (the H480's), and a
    # trim the twin does not hold is a per-motor error the whole flight long; the model-made trim is 0 where
    # nothing is to be held
    _put_trims(effects, src, dx, dy, lever, arm, how, how, lower_bounds=False, support=support)
    return dx, dy, lever


#: a sample is "at the top of the command range" with a motor at or above this normalised command
TOP_COMMAND = 0.9
#: the top is reported as checked with at least this many seconds of such samples
TOP_MIN_S = 2.0
#: at a nearly steady height [m/s, body z]
TOP_VZ_MAX = 0.5


def _thrust_at_top(log: FlightLog, t: np.ndarray, sig: dict, m: float, t_max_rotor: np.ndarray, f_fac: float,
                   battery, cutoff_hz: float, tau: float) -> tuple[str, dict[str, float]]:
    """The thrust the identified map gives at the top of the command range, checked against the flight:
    on the airborne samples (``t``, ``sig``: the whole grid, saturated samples included, ground contact
    left out, at a nearly steady height) the body z equation ``m f_z = c T_map - k_z v_z`` with one ``c`` for
    the samples with a motor
    at >= ``TOP_COMMAND`` and one for the rest (``T_map``: the identified map's thrust of the logged commands
    through the motor lag ``tau``, the battery term included): ``c_top`` and ``c_bulk`` with their standard
    errors (1: the map is right there);
    or, where the flight has less
    than ``TOP_MIN_S`` there, how far up its commands reach.  A check, not a fit: the ratio is not applied
    (a vehicle's ratio there differs from flight to flight with the climb rate and the ground; see
    docs/yaw_authority_fleet.md)."""
    u = np.asarray(sig["motors"], float)
    fz = np.asarray(sig["f_body"], float)[:, 2]
    ok = np.isfinite(u).all(axis=1) & np.isfinite(fz) & contact_mask(log, t, GRID_HZ)
    scale = np.ones(t.size)
    bv = log.get("battery_v") if battery is not None else None
    if bv is not None:
        v = bv.at(t).reshape(-1)
        ok &= np.isfinite(v)
        scale = np.clip(np.nan_to_num(v, nan=battery[2]) / battery[2], 0.3, 1.5) ** battery[3]
    uc = np.clip(np.nan_to_num(u), 0.0, 1.0)
    reach = float(np.percentile(uc[ok].max(axis=1), 99)) if ok.any() else math.nan
    # the rotor states the commands give through the identified lag, and both sides low-passed alike: a
    # command spike is not yet thrust (selecting on raw commands >= 0.9 read 0.91 on a simulated flight
    # whose map is exact)
    segs = _segments(t, GRID_HZ)
    states = np.zeros_like(uc)
    inside = np.zeros(t.size, bool)
    for sg in segs:
        states[sg] = rotor_states_from_commands(t[sg], uc[sg], tau_up_s=tau)
        inside[sg] = True

    def lp(x: np.ndarray) -> np.ndarray:
        return _per_segment(lambda _t, y: lowpass(y, GRID_HZ, cutoff_hz), t, x, segs)

    model = (thrust_regressor(states, "thrust_factor", f_fac) @ t_max_rotor) * scale
    v_up = lp(world_to_body(sig["q"], np.nan_to_num(np.asarray(sig["v_enu"], float)))[:, 2])
    f_lp, t_lp = lp(np.where(ok, m * fz, 0.0)), lp(np.where(ok, model, 0.0))
    # samples of nearly steady height only: in a climb the vertical drag and a map wrong at the top are
    # one regressor (on a simulated flight whose map was given linear for a convex truth, the fit on every
    # sample read half the truth's deviation; below 0.5 m/s it reads it within 0.1 %)
    ok &= inside & (np.abs(v_up) < TOP_VZ_MAX)
    top = ok & (lp(states.max(axis=1)) >= TOP_COMMAND) & (t_lp > 0)
    fits = {"top_command_p99": reach, "top_seconds": float(top.sum()) / GRID_HZ}
    if top.sum() < TOP_MIN_S * GRID_HZ:
        return (f"not reached: {fits['top_seconds']:.1f} s with a motor at >= {TOP_COMMAND:g} of full command "
                f"at a steady height (|v_z| < {TOP_VZ_MAX:g} m/s; needs {TOP_MIN_S:g} s; the airborne motor commands "
                f"reach {reach:.2f}, 99th percentile): above, the thrust is the map extrapolated"), fits
    # m f_z = c_bulk T_map (below the top) + c_top T_map (at the top) - k_z v_z, fitted together: the
    # vertical drag is not taken from the map's own fit (a map wrong at the top leaves its error in k_z there)
    w = top[ok].astype(float)
    fit = fit_linear(np.column_stack([t_lp[ok] * (1.0 - w), t_lp[ok] * w, -v_up[ok]]), f_lp[ok],
                     ["c_bulk", "c_top", "k_z"])
    if fit.rank < 3 or fit.cov is None or not fit["c_bulk"] > 0:
        return "not determined: the top and the rest of the flight are not separable in the fit", fits
    # the low-passed samples are correlated over ~1/(2 cutoff): the fit's covariance is scaled by that many
    inflate = math.sqrt(GRID_HZ / (2.0 * cutoff_hz))
    c_top, c_bulk = float(fit["c_top"]), float(fit["c_bulk"])
    se_top, se_bulk = fit.se("c_top") * inflate, fit.se("c_bulk") * inflate
    fits.update(top_thrust_ratio=c_top, top_thrust_ratio_se=se_top, bulk_thrust_ratio=c_bulk,
                bulk_thrust_ratio_se=se_bulk)
    return (f"checked on {fits['top_seconds']:.1f} s with a motor at >= {TOP_COMMAND:g} of full command at a steady "
            f"height (|v_z| < {TOP_VZ_MAX:g} m/s, saturated samples included): the thrust there is {c_top:.3f} ± "
            f"{se_top:.3f} of the map's ({c_bulk:.3f} ± {se_bulk:.3f} below the top; body z specific force with a "
            f"vertical drag, fitted together); not applied to the map"), fits


def _horizontal_drag(t, sig, lp, f_lp, v_body, m, src):
    """The isotropic horizontal drag fit with a steady wind (see nominal_from_log):
    (drag [N/(m/s)], its stderr, wind or None, east and north unit vectors in the body frame)."""
    nz = np.zeros(t.size)
    one = np.ones(t.size)
    east_b = lp(world_to_body(sig["q"], np.tile([1.0, 0.0, 0.0], (t.size, 1))))
    north_b = lp(world_to_body(sig["q"], np.tile([0.0, 1.0, 0.0], (t.size, 1))))
    X = np.vstack([np.column_stack([-v_body[:, 0], east_b[:, 0], north_b[:, 0], one, nz]),
                   np.column_stack([-v_body[:, 1], east_b[:, 1], north_b[:, 1], nz, one])])
    hfit = fit_linear(X, np.concatenate([f_lp[:, 0], f_lp[:, 1]]), ["kd/m", "kd/m*w_e", "kd/m*w_n", "bias_x",
                                                                      "bias_y"])
    wind = _wind(hfit)
    if wind is None:
        X = X[:, [0, 3, 4]]
        hfit = fit_linear(X, np.concatenate([f_lp[:, 0], f_lp[:, 1]]), ["kd/m", "bias_x", "bias_y"])
        src["effects.wind"] = (f"not included: no steady wind separable from the accelerometer biases (heading "
                               f"change, > 3 sigma, {WIND_MIN_M_S}-15 m/s)")
    return m * hfit["kd/m"], m * hfit.se("kd/m"), wind, east_b, north_b


def _vehicle_fits(rot: dict, t_max: float, km: float, m: float, drag_se: float, near, at_edge: bool, battery,
                  dx: float, dy: float, lever: float, tt_steady: np.ndarray) -> dict:
    """The values a vehicle twin pools over flights, each with its standard error where the fit gives one
    (``<name>_se``): the control effectiveness T_max/I per axis [1/(s^2)] (1 / the moment fit's I/T_max:
    independent of the assumed mass), the lag's near-best range, the drag's se, the static trims and each
    motor's share of the steady-flight thrust (mean 1)."""
    out: dict[str, float] = {"mass_assumed_kg": m, "drag_n_s_m_se": float(drag_se),
                             "tau_near_lo_s": float(near.min()), "tau_near_hi_s": float(near.max()),
                             "tau_at_edge": float(at_edge), "com_dx_m": dx, "com_dy_m": dy, "yaw_lever_m": lever}
    for ax, scale in (("roll", t_max), ("pitch", t_max), ("yaw", t_max * km)):
        i_over, se = rot[ax]["I"] / scale, rot[ax].se("I") / scale
        ok = i_over > 0 and math.isfinite(i_over)
        out[f"{ax}_eff"] = 1.0 / i_over if ok else math.nan
        out[f"{ax}_eff_se"] = se / i_over ** 2 if ok else math.nan
    if battery is not None:
        out["battery_exponent"], out["battery_exponent_se"] = float(battery[3]), float(battery[4])
    share = np.median(tt_steady, axis=0)
    share = share / share.mean() if share.mean() > 0 else share * math.nan
    for i, x in enumerate(share):
        out[f"motor_share_m{i + 1}"] = float(x)
    return out


def _moment_fits(alpha: np.ndarray, rates: np.ndarray, thrust_units: np.ndarray, geom: RotorGeometry,
                 t_max: float, km: float) -> dict:
    """Per axis, the rotor moment [N m] from the commands regressed on [alpha, w, 1]: I, k_w, trim."""
    T = t_max * thrust_units
    moments = {"roll": T @ np.asarray(geom.y_flu_m), "pitch": -(T @ np.asarray(geom.x_flu_m)),
               "yaw": -km * (T @ np.asarray(geom.direction, float))}
    out = {}
    for k, ax in enumerate(("roll", "pitch", "yaw")):
        X = np.column_stack([alpha[:, k], rates[:, k], np.ones(alpha.shape[0])])
        out[ax] = fit_linear(X, moments[ax], ["I", "k_w", "trim"])
    return out


def _wind(hfit) -> tuple[float, float, float] | None:
    """(east, north, stderr) [m/s] of the steady wind from the stacked horizontal drag fit, or None
    where it is not separable (rank), not significant (chi^2 of both > 11.8, 3 sigma), below
    ``WIND_MIN_M_S`` or > 15 m/s."""
    if hfit.rank < len(hfit.names) or hfit.cov is None or not hfit["kd/m"] > 3 * hfit.se("kd/m"):
        return None
    b = np.array([hfit["kd/m*w_e"], hfit["kd/m*w_n"]])
    cb = hfit.cov[1:3, 1:3]
    if not float(b @ np.linalg.solve(cb, b)) > 11.8:
        return None
    a = hfit["kd/m"]
    w = b / a
    if not WIND_MIN_M_S <= float(np.hypot(*w)) < 15.0:
        return None
    return float(w[0]), float(w[1]), float(np.sqrt(np.trace(cb) / 2.0) / a)


def _drag_height(alpha, rates, thrust_units, geom: RotorGeometry, t_max: float, v_air, drag: float,
                 arm: float) -> tuple[float | None, str]:
    """Height [m] above the centre of mass at which the horizontal drag acts, from the roll and pitch
    moment equations stacked (moment form, one shared ``h k``); None where it is not significant
    (|t| < 3) or outside [-arm, arm] (the drag of a multirotor acts near its rotor plane)."""
    T = t_max * thrust_units
    mx = T @ np.asarray(geom.y_flu_m)
    my = -(T @ np.asarray(geom.x_flu_m))
    n = alpha.shape[0]
    z, o = np.zeros(n), np.ones(n)
    X = np.vstack([np.column_stack([alpha[:, 0], z, rates[:, 0], z, o, z, -v_air[:, 1]]),
                   np.column_stack([z, alpha[:, 1], z, rates[:, 1], z, o, v_air[:, 0]])])
    fit = fit_linear(X, np.concatenate([mx, my]), ["Ixx", "Iyy", "kw_x", "kw_y", "trim_x", "trim_y", "hk"])
    hk, se = fit["hk"], fit.se("hk")
    h, h_se = hk / drag, se / drag
    text = f"h {h * 1000:.0f} ± {h_se * 1000:.0f} mm (roll/pitch moment vs air speed)"
    if not (abs(hk) > 3 * se and DRAG_HEIGHT_MIN * arm <= abs(h) <= arm):
        return None, (f"its height above the centre of mass, {text}, is not significant, below "
                      f"{DRAG_HEIGHT_MIN:.0%} of the arm or beyond it")
    return float(h), text


def _battery_sag(log: FlightLog, t: np.ndarray, tt: np.ndarray, lp, v_body: np.ndarray, sig: dict,
                 segs: list[slice]) -> tuple[float, float, float, float, float] | None:
    """(kT/m, its se, V_ref, exponent, its se) when the pack voltage sags enough to matter and the
    fit says so (exponent 3 sigma above 0 and below 4), else None."""
    bv = log.get("battery_v")
    if bv is None or len(bv) < 10:
        return None
    v = bv.at(t).reshape(-1)
    if not np.isfinite(v).all() or np.nanmax(v) - np.nanmin(v) < 0.03 * np.nanmax(v):
        return None
    v_ref = float(np.percentile(v, 99))
    tsum = tt.sum(axis=1)
    X = np.column_stack([tsum, tsum * lp(np.log(np.clip(v / v_ref, 0.3, 1.5))), -v_body[:, 2]])
    fit = fit_linear(X, lp(sig["f_body"])[:, 2], ["kT/m", "kT*e/m", "kd_z/m"])
    c1, c2 = fit["kT/m"], fit["kT*e/m"]
    expo = c2 / c1
    expo_se = fit.se("kT*e/m") / c1
    if not (c1 > 0 and expo > 3 * expo_se and expo < 4.0):
        return None
    return c1, fit.se("kT/m"), v_ref, float(expo), float(expo_se)


def _hover_command(total_thrust_max_n: float, mass_kg: float, f: float, g: float = G_STANDARD_M_S2) -> float:
    """Per-motor command that carries the weight: solve f u^2 + (1 - f) u = m g / (N T_max)."""
    rel = mass_kg * g / total_thrust_max_n
    if f < 1e-9:
        return rel
    return (-(1 - f) + math.sqrt((1 - f) ** 2 + 4 * f * rel)) / (2 * f)


#: the cache key of the code that builds a nominal, taken when it was imported (the source on disk may
#: change under a running process, which must not file its results under the new code's key)
_CODE_KEY = b"".join(inspect.getsource(sys.modules[name]).encode() for name in
                     (__name__, "twin_nodes.identify.regression", "twin_nodes.identify.yaw_gain",
                      "twin_nodes.vehicle.px4_params", "twin_nodes.logs.ulog_io", "twin_nodes.identify.fit_mask",
                      "twin_nodes.identify.coaxial", "twin_nodes.identify.static_trims",
                      "twin_nodes.identify.rate_bound"))

def nominal_once(log: FlightLog):
    """A callable giving ``nominal_from_log(log)``, built at its first call; every later call gives the
    same :class:`Nominal` (or raises the same error again).  The fleet's per-flight facts and the params
    it flies share one build of the same log's nominal through it."""
    memo: list = []

    def build() -> Nominal:
        if not memo:
            try:
                memo.append((True, nominal_from_log(log)))
            except Exception as exc:  # the same failure for every caller, as a fresh build would raise
                memo.append((False, exc))
        ok, value = memo[0]
        if not ok:
            raise value
        return value

    return build


#: PX4 airframes (SYS_AUTOSTART) with a shipped params file: (stem, what it is)
SHIPPED_AIRFRAMES = {10040: "px4_sih_quadx", 1100: "px4_sih_quadx"}


def params_for_log(ulog: str | os.PathLike[str], explicit: str | os.PathLike[str] | None = None,
                   log: FlightLog | None = None, build=None) -> tuple[Path, str | None]:
    """The params file to fly beside ``ulog`` and a one-line note when it was not given (``log``: the
    flight already loaded from ``ulog``, so it is not read again; ``build``: a callable giving
    ``nominal_from_log(log)``, e.g. :func:`nominal_once`'s, called instead when the nominal is to be built).

    ``explicit`` if given; else the shipped file for the log's airframe (SYS_AUTOSTART);
    else the nominal built from the log itself (:func:`nominal_from_log`), written once to
    the private cache folder, keyed on the log's bytes and this module's source."""
    from twin_nodes.base.errors import ParamsError
    from twin_nodes.base.io import cache_dir
    from twin_nodes.logs.ulog_io import read_params
    from twin_nodes.vehicle.params import params_dir, write_params

    if explicit:
        p = Path(explicit)
        if not p.is_file():
            raise ParamsError(str(p), "<file>", "an existing params YAML file")
        return p, None
    params = log.params if log is not None else read_params(ulog)
    autostart = int_param(params, "SYS_AUTOSTART", str(ulog), 0, 99_999_999)
    stem = SHIPPED_AIRFRAMES.get(autostart)
    if stem is not None:
        return params_dir() / f"{stem}.yaml", f"params: shipped {stem}.yaml for SYS_AUTOSTART {autostart}"
    h = hashlib.sha1(Path(ulog).read_bytes())
    h.update(_CODE_KEY)
    out = cache_dir() / "nominal" / f"{Path(ulog).stem}-{h.hexdigest()[:12]}.yaml"
    if not out.is_file():
        nom = build() if build is not None else nominal_from_log(
            log if log is not None else read_flight(ulog, horizontal=False))
        out.parent.mkdir(mode=0o700, exist_ok=True)
        write_params(nom.params, out, nom.header())
    return out, (f"params: none given and no shipped file for SYS_AUTOSTART {autostart}: flying the nominal built "
                 f"from the log itself ({out}; its header lists every value's source; keep one with "
                 f"'rotortwin params from-ulog')")
