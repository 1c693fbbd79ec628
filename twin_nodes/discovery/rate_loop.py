"""The rate loop as PX4 flies it: the body-rate response to the logged rate setpoint.

On a PX4 log with motors logged every 20 ms the commands are aliased (PX4's rate loop runs at
250-800 Hz), so a model driven by them cannot resolve the roll/pitch authority: the output error
leaves those axes out and the rate setpoint as an instrument of the commands is weak on roll
(r 0.4-0.6 on PX4 SIH missions).  The rate setpoint itself is not aliased (it is the attitude
loop's smooth output) and the log carries the rate loop's own gains (``MC_*RATE_P/I/D/FF/K``).
So the twin's rotational axis can be flown the way PX4 flies it: PX4's rate controller, with the
log's gains and PX4's sensor delays, closing the loop on the model's motors and inertia, driven
by the logged setpoint.  Over 1 s windows the simulated body rate is compared with the logged
one; the window's unknowns (the integrator and any steady moment, the motors' and the rate's
state at the start) are free per window and enter linearly.  What remains depends on how fast
the airframe answers a torque: the authority per unit torque setpoint over the inertia, and the
motors' lag and delay.

The closed loop is linear about hover, so every window is simulated once per candidate scale of
the axis's inertia (all windows and scales in one vectorised pass), and any subset of windows
(a fold, a held-out part) is judged from the same simulations.

Delays, from the log's parameters (:func:`twin_nodes.vehicle.px4_params.sensor_timing`): the rate
controller sees the gyro through the ``IMU_GYRO_CUTOFF`` low-pass (its group delay), its D term
the angular acceleration through the ``IMU_DGYRO_CUTOFF`` low-pass; its output is held for one
``IMU_GYRO_RATEMAX`` step.  On the 12 PX4 SIH no-effect flights the inertia read this way is
0.90-1.05 x the model's on roll and 0.95-1.10 on pitch (0.05 grid); roll and pitch inertia
x1.5 read 1.40-1.55, SIH_L_ROLL 0.2 -> 0.16 (roll x1.25) reads 1.10-1.20 on roll, 1.00 on pitch.
Without those delays every axis read 0.85-0.95 on the no-effect flights.  (Those numbers are from the
logged rate setpoint as the input.)

Roll and pitch are read with PX4's attitude loop closed on the simulated rate (:func:`with_attitude_loop`;
ninth session, ``docs/discovery.md``): the logged rate setpoint is the attitude loop's answer to the
vehicle's own motion, and in windows where it is mostly regulation (hover, the return and landing) the
inertia read low: roll x0.75-0.85 in windows of 0.02-0.04 rad/s
setpoint standard deviation on three no-effect grid flights (s051, s055, s060), x1.00-1.23 above 0.08;
SIH_L_ROLL 0.15 (x1.31, h004) 0.96 there and 1.34 above 0.08.  The held-out last 30 % of a flight (the
return: half the excitation) then read lower than the part fitted.  With the attitude loop the 18 grid
no-effect flights read roll 0.92-1.04 and pitch 0.96-1.10 (0.89-1.01 and 0.93-1.09 before), the
shared e05 (roll/pitch x1.3) 1.28/1.33 (1.20/1.32 before).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from twin_nodes.physics.effects import effective_params
from twin_nodes.vehicle.params import VehicleParams
from twin_nodes.discovery.output_error import IV_AXIS_PARAM
from twin_nodes.vehicle.px4_params import RateGainsPx4, param, sensor_timing, torque_moments

AXES = ("roll", "pitch", "yaw")
#: window length and stride [s]: long enough for the rate loop to settle (closed-loop time
#: constant ~0.12 s on PX4 SIH), short enough that the per-window nuisances stay constants
WINDOW_S = 1.0
STRIDE_S = 0.5
#: integration step of the closed loop [s] (the delays are multiples of it)
STEP_S = 0.002
#: the inertia scales every window is simulated at (log-spaced, x0.5 .. x2.0, ~4.7 % apart);
#: the minimum is refined by a parabola in log scale
SCALES = np.exp(np.linspace(math.log(0.5), math.log(2.0), 31))
#: consecutive windows that share data (50 % overlap) are one cluster for standard errors
CLUSTER = 3
#: windows simulated at once (a 14-minute flight has ~1700)
CHUNK = 400


@dataclass(frozen=True)
class RateLoop:
    """PX4's rate loop on the model's airframe, per axis (roll, pitch, yaw)."""

    p: np.ndarray            # (3,) normalised torque per rad/s
    i: np.ndarray            # (3,) normalised torque per rad
    d: np.ndarray            # (3,) normalised torque per rad/s^2
    ff: np.ndarray           # (3,) normalised torque per rad/s of setpoint
    authority: np.ndarray    # (3,) rad/s^2 per unit torque setpoint at the model's inertia
    damping: np.ndarray      # (3,) 1/s: angular damping over the inertia
    tau_s: float             # the motors' lag (mean of up and down)
    feedback_delay_s: float  # the gyro low-pass's group delay
    d_delay_s: float         # the angular-acceleration low-pass's group delay (D term)
    command_delay_s: float   # the rate-loop hold plus the model's actuator delay
    output_tau_s: np.ndarray  # (3,) first-order low-pass on the torque setpoint (yaw: MC_YAW_TQ_CUTOFF)
    sources: tuple[str, ...] = ()
    #: (3,) the attitude loop's P gain [1/s] (MC_ROLL_P, MC_PITCH_P), closed around the simulated rate where
    #: > 0 (:func:`simulate`'s ``w_in``); zero: the logged rate setpoint drives the rate loop as it is
    att_p: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def describe(self) -> dict:
        return {"p": [round(float(x), 4) for x in self.p], "i": [round(float(x), 4) for x in self.i],
                "d": [round(float(x), 5) for x in self.d], "ff": [round(float(x), 4) for x in self.ff],
                "authority_rad_s2": [round(float(x), 2) for x in self.authority],
                "tau_s": round(self.tau_s, 4), "feedback_delay_ms": round(1e3 * self.feedback_delay_s, 2),
                "d_delay_ms": round(1e3 * self.d_delay_s, 2), "command_delay_ms": round(1e3 * self.command_delay_s, 2),
                "torque_lowpass_s": [round(float(x), 4) for x in self.output_tau_s],
                "sources": list(self.sources)}


def _thrust_slope(vp: VehicleParams) -> float:
    """dT/du of one rotor at hover [N per unit command] (the steady-state command -> thrust map)."""
    r = vp.rotors
    u = vp.hover_command
    if r.thrust_model == "omega_squared":
        omega = r.omega_min_rad_s + u * (r.omega_cmd_max_rad_s - r.omega_min_rad_s)
        return float(2.0 * r.kt_n_s2_rad2 * omega * (r.omega_cmd_max_rad_s - r.omega_min_rad_s))
    f = r.thr_mdl_fac
    return float(r.thrust_max_n * (2.0 * f * u + 1.0 - f))


def rate_loop(params: Mapping[str, float], vp: VehicleParams) -> RateLoop | None:
    """The rate loop of a PX4 log (its parameters ``params``) on the airframe ``vp`` (its effects
    applied); None when the log is not PX4's (no ``MC_ROLLRATE_P``: our own and RotorPy logs)."""
    if "MC_ROLLRATE_P" not in params:
        return None
    e = effective_params(vp)
    g = RateGainsPx4.from_params(params)
    ff = []
    for ax in ("ROLL", "PITCH", "YAW"):
        k = param(params, f"MC_{ax}RATE_K", 1.0)[0]
        ff.append(k * param(params, f"MC_{ax}RATE_FF", 0.0)[0])
    yaw_d = param(params, "MC_YAWRATE_K", 1.0)[0] * param(params, "MC_YAWRATE_D", 0.0)[0]
    r = e.rotors
    km_px4 = abs(param(params, "CA_ROTOR0_KM", 0.05)[0]) or 0.05
    moment = torque_moments(np.array(r.x_flu_m), np.array(r.y_flu_m), np.array(r.direction, float), km_px4,
                            _thrust_slope(e), r.km_m)
    inertia = np.diag(e.inertia)
    damp = e.effect_dict.get("angular_damping", {}).get("k_nm_s_rad", 0.0)
    timing = sensor_timing(params)
    fd = param(params, "IMU_DGYRO_CUTOFF", 0.0)[0]
    d_delay = math.sqrt(2.0) / (2.0 * math.pi * fd) if fd > 0 else timing.gyro_filter_s
    act = e.effect_dict.get("actuator_delay", {}).get("delay", 0.0)
    yaw_fc = param(params, "MC_YAW_TQ_CUTOFF", 0.0)[0]
    out_tau = np.array([0.0, 0.0, 1.0 / (2.0 * math.pi * yaw_fc) if yaw_fc > 0 else 0.0])
    src = (f"gains: {', '.join(sorted({s for s in g.sources}))}",
           f"feedback {1e3 * timing.gyro_filter_s:.1f} ms (IMU_GYRO_CUTOFF group delay), D term {1e3 * d_delay:.1f} ms "
           f"(IMU_DGYRO_CUTOFF), command {1e3 * (timing.command_hold_s + act):.1f} ms (rate-loop step hold"
           + (f" + the model's {1e3 * act:.1f} ms actuator delay" if act else "") + ")"
           + (f"; yaw torque low-pass {yaw_fc:g} Hz (MC_YAW_TQ_CUTOFF)" if yaw_fc > 0 else ""))
    return RateLoop(p=np.array([g.roll_p, g.pitch_p, g.yaw_p]), i=np.array([g.roll_i, g.pitch_i, g.yaw_i]),
                    d=np.array([g.roll_d, g.pitch_d, yaw_d]), ff=np.array(ff), authority=moment / inertia,
                    damping=damp / inertia, tau_s=0.5 * (r.tau_up_s + r.tau_down_s),
                    feedback_delay_s=timing.gyro_filter_s, d_delay_s=d_delay,
                    command_delay_s=timing.command_hold_s + act, output_tau_s=out_tau, sources=src)


def make_windows(t: np.ndarray, valid: np.ndarray, w: np.ndarray, w_sp: np.ndarray, dt: float,
                 window_s: float = WINDOW_S, stride_s: float = STRIDE_S) -> tuple[np.ndarray, int]:
    """Window starts (every sample valid and finite) and the window length in samples."""
    n = int(round(window_s / dt))
    st = max(1, int(round(stride_s / dt)))
    starts = np.arange(0, len(t) - n - 1, st)
    ok = np.isfinite(w).all(1) & np.isfinite(w_sp).all(1) & np.asarray(valid, bool)
    bad = np.concatenate([[0], np.cumsum(~ok)])
    keep = (bad[starts + n + 1] - bad[starts]) == 0
    return starts[keep], n


def simulate(loop: RateLoop, axis: int, sp: np.ndarray, dt: float, scales: np.ndarray,
             step_s: float = STEP_S, taus: np.ndarray | None = None, w_in: np.ndarray | None = None) -> np.ndarray:
    """Body-rate trajectories (S, 4, K, n + 1) of the closed loop on ``axis`` for each inertia
    scale (or, with ``taus``, each motor time constant at the model's inertia), from the setpoint
    ``sp`` (K, n + 1) on the grid (linear in between): mode 0 the response to the setpoint from
    rest, modes 1-3 to a unit steady torque (integrator) offset, a unit initial motor torque, a unit
    initial rate (the per-window nuisances).  With ``w_in`` (the logged rate, K, n + 1) and ``att_p`` > 0
    the attitude loop is closed on the simulated rate: the setpoint flown is ``sp + att_p integral(w_in -
    w_sim)`` = ``att_p (angle_sp - angle_sim)`` (the logged one is ``att_p (angle_sp - angle)``), so the
    input is the attitude setpoint, not a rate setpoint that answers the vehicle's own motion."""
    if taus is not None:
        scales = np.ones(len(taus))
    K, n1 = sp.shape
    sub = max(1, int(round(dt / step_s)))
    h = dt / sub
    a = loop.authority[axis] / scales[:, None, None]                   # (S, 1, 1)
    kd = loop.damping[axis] / scales[:, None, None]
    P, I, D, FF = loop.p[axis], loop.i[axis], loop.d[axis], loop.ff[axis]
    pa = float(loop.att_p[axis]) if w_in is not None else 0.0
    lf = int(round(loop.feedback_delay_s / h))
    ld = int(round(loop.d_delay_s / h))
    lc = int(round(loop.command_delay_s / h))
    L = max(lf, ld, lc) + 1
    shape = (len(scales), 4, K)
    ang = np.zeros(shape)                                               # integral of (w_in - w_sim)
    om = np.zeros(shape)
    om[:, 3] = 1.0
    m = np.zeros(shape)
    m[:, 2] = 1.0
    integ = np.zeros(shape)
    offset = np.zeros((1, 4, 1))
    offset[0, 1, 0] = 1.0
    al = a * m - kd * om
    # ring buffers of the rate, the angular acceleration and the command (the delays)
    hist_om = np.repeat(om[None], L, 0)
    hist_al = np.repeat(al[None], L, 0)
    hist_u = np.zeros((L,) + shape)
    hist_u[:, :, 2] = 1.0
    out = np.empty((n1,) + shape)
    out[0] = om
    gate = np.zeros((1, 4, 1))
    gate[0, 0, 0] = 1.0
    k = 0
    # first-order lags stepped exactly (a lag shorter than the step follows its input)
    tau = np.asarray([loop.tau_s] if taus is None else taus, float)
    k_m = np.where(tau > 0, -np.expm1(-h / np.maximum(tau, 1e-12)), 1.0)[:, None, None]
    lp = float(loop.output_tau_s[axis])
    k_lp = -math.expm1(-h / lp) if lp > 0 else 1.0
    # the torque low-pass (yaw): its state starts at the window's steady output (the offset and
    # the initial motor torque are what PX4 had been commanding)
    y_lp = np.zeros(shape)
    y_lp[:, 1] = 1.0
    y_lp[:, 2] = 1.0
    for j in range(n1 - 1):
        for s in range(sub):
            f = s / sub
            spj = (sp[:, j] * (1.0 - f) + sp[:, j + 1] * f)[None, None, :] * gate
            if pa > 0.0:
                spj = spj + pa * ang
            om_fb = hist_om[(k - lf) % L]
            al_fb = hist_al[(k - ld) % L]
            e = spj - om_fb
            u = P * e + integ + offset - D * al_fb + FF * spj
            integ = integ + I * e * h
            if lp > 0.0:
                y_lp = y_lp + (u - y_lp) * k_lp
                u = y_lp
            hist_u[k % L] = u
            u_applied = hist_u[(k - lc) % L]
            m = m + (u_applied - m) * k_m
            al = a * m - kd * om
            if pa > 0.0:
                ang = ang + ((w_in[:, j] * (1.0 - f) + w_in[:, j + 1] * f)[None, None, :] * gate - om) * h
            om = om + al * h
            k += 1
            hist_om[k % L] = om
            hist_al[k % L] = al
        out[j + 1] = om
    return np.moveaxis(out, 0, -1)                                      # (S, 4, K, n + 1)


def residuals(loop: RateLoop, axis: int, w: np.ndarray, sp: np.ndarray, dt: float,
              scales: np.ndarray = SCALES, taus: np.ndarray | None = None) -> np.ndarray:
    """(S, K, n) residual of the logged body rate ``w`` (K, n + 1) against the closed loop at
    each scale (or motor time constant, ``taus``), after the per-window nuisances (steady torque,
    initial motor torque, initial rate) are fitted by least squares on the window's samples 1..n.
    Long flights go through in chunks of ``CHUNK`` windows (memory: the trajectories of every scale
    and mode of a chunk, ~50 MB)."""
    if len(w) > CHUNK:
        return np.concatenate([residuals(loop, axis, w[k:k + CHUNK], sp[k:k + CHUNK], dt, scales, taus)
                               for k in range(0, len(w), CHUNK)], axis=1)
    traj = simulate(loop, axis, sp, dt, scales, taus=taus, w_in=w if loop.att_p[axis] > 0 else None)
    F, B = traj[:, 0, :, 1:], traj[:, 1:, :, 1:]                        # (S,K,n), (S,3,K,n)
    Y = w[None, :, 1:] - F
    A = np.moveaxis(B, 1, -1)                                           # (S,K,n,3)
    AtA = np.einsum("skni,sknj->skij", A, A) + 1e-12 * np.eye(3)
    Aty = np.einsum("skni,skn->ski", A, Y)
    try:
        c = np.linalg.solve(AtA, Aty[..., None])[..., 0]
    except np.linalg.LinAlgError:  # a scale whose loop diverges (flown gains at too small an inertia): least norm
        c = (np.linalg.pinv(AtA) @ Aty[..., None])[..., 0]
    return Y - np.einsum("skni,ski->skn", A, c)


def parabola_min(y: np.ndarray, x: np.ndarray) -> tuple[float, float, bool]:
    """The minimum of ``y`` over the grid ``x``, refined by a parabola through the grid's minimum and its two
    neighbours (moved at most one grid step): (x, y, whether it is inside the grid)."""
    i = int(np.argmin(y))
    if not 0 < i < len(y) - 1:
        return float(x[i]), float(y[i]), False
    y0, y1, y2 = y[i - 1], y[i], y[i + 1]
    den = y0 - 2 * y1 + y2
    off = float(np.clip(0.5 * (y0 - y2) / den, -1, 1)) if den > 0 else 0.0
    h = x[i + 1] - x[i] if off >= 0 else x[i] - x[i - 1]
    return float(x[i] + off * h), float(y1 - 0.25 * (y0 - y2) * off), True


def fit_scale(R: np.ndarray, scales: np.ndarray, rows: np.ndarray) -> tuple[float, float]:
    """The inertia scale minimising the residual over the windows ``rows`` (parabola in log scale
    through the grid's minimum) and its standard error (clustered Gauss-Newton sandwich)."""
    idx = np.flatnonzero(rows)
    if idx.size < 2 * CLUSTER:
        return math.nan, math.nan
    sse = np.einsum("skn,skn->s", R[:, idx], R[:, idx])
    i = int(np.argmin(sse))
    x, _, interior = parabola_min(sse, np.log(scales))
    if not interior:
        return float(scales[i]), math.nan                                # at the grid's edge
    s_hat = float(math.exp(x))
    u, A, sd = _score(R, scales, i, idx, R[i, idx])
    return s_hat, (sd / A if A > 0 else math.nan)


def _score(R: np.ndarray, scales: np.ndarray, i: int, idx: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Per window ``<J_k, e_k>`` of the residual ``e`` with its sensitivity J at grid point ``i`` (central
    difference), ``sum |J|^2``, and the clustered standard deviation of the windows' sum."""
    J = (R[i + 1, idx] - R[i - 1, idx]) / (scales[i + 1] - scales[i - 1])   # (k, n) d resid / d s
    u = np.einsum("kn,kn->k", J, e)
    c = u.size // CLUSTER * CLUSTER
    U = np.add.reduceat(u[:c], np.arange(0, c, CLUSTER)) if c else u
    return u, float(np.sum(J * J)), float(math.sqrt(float(np.sum(U ** 2))))


def projected(R: np.ndarray, scales: np.ndarray, s: float, rows: np.ndarray) -> tuple[float, float]:
    """The residual along its own sensitivity to the inertia, at scale ``s`` over ``rows``:
    ``|sum_k <J_k, e_k>| / sqrt(sum_k |J_k|^2)`` [rad/s] (the part of the rate error a change of
    inertia would explain; the gyro noise, independent of it, averages out), and the score
    statistic of ``s`` (that sum over its clustered standard error)."""
    idx = np.flatnonzero(rows)
    if idx.size < 2 * CLUSTER or not np.isfinite(s):
        return math.nan, math.nan
    ls = np.log(scales)
    x = math.log(s)
    i = int(np.clip(np.searchsorted(ls, x), 1, len(scales) - 2))
    # the residual at s, linear between the grid points around it
    lo = i - 1 if x < ls[i] else i
    w = (x - ls[lo]) / (ls[lo + 1] - ls[lo])
    u, A, sd = _score(R, scales, i, idx, (1 - w) * R[lo, idx] + w * R[lo + 1, idx])
    return (abs(float(u.sum())) / math.sqrt(A) if A > 0 else math.nan,
            float(u.sum()) / sd if sd > 0 else math.nan)


#: an axis's inertia is flagged when the rate loop reads it this far from the model's (and
#: ``MIN_SE`` standard errors): on the 12 PX4 SIH no-effect flights and the 25 flights whose effect
#: leaves roll and pitch alone (mass, drag, yaw moment, Izz) roll reads 0.89-1.01 and pitch
#: 0.96-1.07; SIH_L_ROLL 0.16 (roll x1.25) reads 1.10-1.21, roll/pitch x1.3 1.20/1.32, x1.5 1.41-1.55
#: (from the rate setpoint; with the attitude loop the grid's no-effect roll reads 0.92-1.04, kept as is)
MIN_CHANGE = 0.10
MIN_SE = 4.0
#: the yaw axis read off the same way as a flagged roll/pitch axis (beyond ``MOTOR_YAW_SE``
#: standard errors): the motors (a lag or a delay) act on every axis, an inertia on its own.  PX4
#: SIH SIH_T_TAU 0.09-0.12 s: yaw 1.08-1.17; the no-effect flights 0.99-1.05
MOTOR_YAW_CHANGE = 0.03
MOTOR_YAW_SE = 3.0
#: a roll/pitch axis flagged beside a larger flagged one must move this far (rll12): on 91 axes of PX4 SIH
#: batches 1-8 the flight left at x1 (no-effect flights, the other axis of an arm change, mass, drag, Izz,
#: damping) the rate loop reads 1.011 +- 0.045 (0.91-1.15) with standard errors of 0.01-0.05, the same on
#: roll-arm flights (pitch 0.93-1.10) as on no-effect ones (0.91-1.15): a flight-level scatter, not the arm
#: (PX4's allocation and SIH's moments leave pitch alone); two axes changed together read 1.27-1.68
MIN_CHANGE_BESIDE = 0.15


def projected_folds(R: np.ndarray, scales: np.ndarray, parts: list[tuple[float, np.ndarray]]) -> tuple[float, float]:
    """:func:`projected` over the held-out windows of both folds, each at its own fold's scale: ``parts`` is
    ``[(s, rows), ...]``; the sums ``<J_k, e_k>`` and ``|J_k|^2`` and the clustered variances add over the parts
    (a part with fewer than ``2 CLUSTER`` windows adds nothing).  A held-out part the flight barely excites on
    the axis (small ``|J|^2``) weighs little: PX4 SIH's take-off-and-land mission M5 holds out its descent
    and landing, where pitch carries a quarter of the information of the take-off (m018: 0.18 against 0.75),
    and fold 1's pitch cut there is noise (-301 %), the two folds' 84 %."""
    u_sum, A_sum, var = 0.0, 0.0, 0.0
    ls = np.log(scales)
    for s, rows in parts:
        idx = np.flatnonzero(rows)
        if idx.size < 2 * CLUSTER or not np.isfinite(s):
            continue
        x = math.log(s)
        i = int(np.clip(np.searchsorted(ls, x), 1, len(scales) - 2))
        lo = i - 1 if x < ls[i] else i
        w = (x - ls[lo]) / (ls[lo + 1] - ls[lo])
        u, A, sd = _score(R, scales, i, idx, (1 - w) * R[lo, idx] + w * R[lo + 1, idx])
        u_sum, A_sum, var = u_sum + float(u.sum()), A_sum + A, var + sd * sd
    if A_sum <= 0:
        return math.nan, math.nan
    return abs(u_sum) / math.sqrt(A_sum), (u_sum / math.sqrt(var) if var > 0 else math.nan)


def with_attitude_loop(loop: RateLoop, params: Mapping[str, float]) -> RateLoop:
    """``loop`` with PX4's attitude loop closed on roll and pitch (``MC_ROLL_P``, ``MC_PITCH_P``; yaw as it
    was; :func:`simulate`'s ``w_in``)."""
    kp = [param(params, k, 0.0)[0] for k in ("MC_ROLL_P", "MC_PITCH_P")]
    return dataclasses.replace(loop, att_p=np.array([max(kp[0], 0.0), max(kp[1], 0.0), 0.0]))


def _flight(data, params: Mapping[str, float], vp: VehicleParams, t_split: float, t_split2: float):
    """The rate loop of a PX4 log on ``vp``, its windows' grid samples (K, n + 1), and the window
    masks (all, fold 1 fit, fold 1 held out, fold 2 fit: a window belongs to a part when all of it
    does; fold 2 holds out the windows before ``t_split2``, the fifth mask); None without PX4's rate loop, a rate
    setpoint, or 20 windows."""
    loop = rate_loop(params, vp)
    if loop is None or data.w_sp is None:
        return None
    starts, n = make_windows(data.t, data.valid_attitude, data.w, data.w_sp, data.dt)
    if starts.size < 20:
        return None
    idx = starts[:, None] + np.arange(n + 1)[None, :]
    t0, t1 = data.t[starts], data.t[starts + n]
    return loop, idx, (np.ones(starts.size, bool), t1 < t_split, t0 >= t_split, t0 >= t_split2, t1 < t_split2)


def inertia(data, params: Mapping[str, float], vp: VehicleParams, t_split: float, t_split2: float,
            axes_allowed: tuple[str, ...] = ("roll", "pitch")) -> dict | None:
    """Roll/pitch inertia from PX4's rate loop flown on the model ``vp`` (:func:`rate_loop`) and
    driven by the logged rate setpoint, in the form
    :func:`twin_nodes.discovery.output_error.instrumented_inertia` gives (``gain`` is the
    authority per command over the model's, ``1 / scale``; ``params`` the inertia fold 1's fit asks
    for; ``heldout_*`` the held-out windows of both folds, each at its own fold's fit, the residual along
    its sensitivity to the inertia, :func:`projected_folds`).  Fold 1 fits the windows before ``t_split``
    and holds out those after; fold 2 fits those after ``t_split2`` and holds out those before (a window
    belongs to a part when all of it does).  ``None``
    when the log is not PX4's, has no rate setpoint, or too few windows."""
    setup = _flight(data, params, vp, t_split, t_split2)
    if setup is None:
        return None
    loop, idx, (every, fit1, test1, fit2, test2) = setup
    loop = with_attitude_loop(loop, params)
    I0 = np.diag(effective_params(vp).inertia).astype(float)
    out = {"method": "rate_loop", "loop": loop.describe(), "windows": int(idx.shape[0]),
           "window_s": WINDOW_S, "axes": {}}
    for ax, name in enumerate(AXES):
        if name != "yaw" and name not in axes_allowed:
            continue
        R = residuals(loop, ax, data.w[idx, ax], data.w_sp[idx, ax], data.dt)
        s, se = fit_scale(R, SCALES, every)
        out.setdefault("curve", {"scales": [round(float(x), 4) for x in SCALES]})[name] = _relative_sse(R)
        if name == "yaw":
            out["yaw_gain"], out["yaw_se"] = _gain(s, se)
            out["yaw_scale"], out["yaw_scale_se"] = s, se
            continue
        s1, se1 = fit_scale(R, SCALES, fit1)
        s2, se2 = fit_scale(R, SCALES, fit2)
        g, sg = _gain(s, se)
        g1, sg1 = _gain(s1, se1)
        g2, sg2 = _gain(s2, se2)
        # held out: each fold's held-out windows at that fold's fit (the last 30 % at fold 1's, the first 30 %
        # at fold 2's), pooled (:func:`projected_folds`)
        b, tb = projected_folds(R, SCALES, [(1.0, test1), (1.0, test2)])
        a, ta = projected_folds(R, SCALES, [(s1, test1), (s2, test2)])
        flagged = bool(np.isfinite(s) and np.isfinite(se) and abs(s - 1.0) > max(MIN_CHANGE, MIN_SE * se))
        out["axes"][name] = {"index": 3 + ax, "gain": g, "se": sg, "scale": s, "scale_se": se,
                             "gain_fold1": g1, "se_fold1": sg1, "gain_fold2": g2, "se_fold2": sg2,
                             "flagged": flagged, "heldout_before": b, "heldout_after": a,
                             "heldout_t": abs(tb) if np.isfinite(tb) else math.nan,
                             "heldout_t_after": abs(ta) if np.isfinite(ta) else math.nan}
    axes = out["axes"]
    if not axes:
        return None
    # an axis read at the edge of the scales (x0.5 or x2) is not this vehicle's rate loop (on real
    # logs with a nominal from the log itself: the S500's pitch and yaw); then nothing is read from it
    out["pinned"] = ([a for a, d in axes.items() if not np.isfinite(d["scale_se"])]
                     + ([] if np.isfinite(out["yaw_scale_se"]) else ["yaw"]))
    if out["pinned"]:
        out["flagged"] = []
        return out
    flagged = beside_flagged(axes)
    out["flagged"] = flagged
    if not flagged:
        return out
    out["motor_signature"] = motor_signature(axes, flagged, out.get("yaw_scale", math.nan),
                                             out.get("yaw_scale_se", math.nan))
    new = I0.copy()
    for a in flagged:
        j = IV_AXIS_PARAM[a][1]
        new[j] = I0[j] * (1.0 / axes[a]["gain_fold1"]) if np.isfinite(axes[a]["gain_fold1"]) else math.nan
    out["params"] = {"ixx": float(new[0]), "iyy": float(new[1]), "izz": float(I0[2])}
    return out


def beside_flagged(axes: dict) -> list[str]:
    """The flagged axes of ``axes`` (each ``scale``, ``flagged``), an axis beside a larger flagged one kept only
    where it moves ``MIN_CHANGE_BESIDE`` (else unflagged, ``beside`` says why).  PX4 SIH z011 (SIH_L_ROLL 0.17,
    roll x1.18): roll x1.16, pitch x1.10 +- 0.02 (flagged: Iyy 14.5 % off), z023 (no effect) pitch x1.10."""
    flagged = [a for a, d in axes.items() if d["flagged"]]
    top = max(flagged, key=lambda a: abs(axes[a]["scale"] - 1.0), default=None)
    for a in [a for a in flagged if a != top and abs(axes[a]["scale"] - 1.0) <= MIN_CHANGE_BESIDE]:
        axes[a]["flagged"] = False
        axes[a]["beside"] = f"x{axes[a]['scale']:.3f} beside {top} x{axes[top]['scale']:.3f}: within {MIN_CHANGE_BESIDE:g}"
        flagged.remove(a)
    return flagged


def motor_signature(axes: dict, flagged: list[str], sy: float, sey: float) -> bool:
    """Whether yaw (inertia scale ``sy`` +- ``sey``) reads off the same way as a flagged roll/pitch axis of
    ``axes`` (beyond ``MOTOR_YAW_CHANGE`` and ``MOTOR_YAW_SE`` standard errors): the motors, not an inertia."""
    same = [a for a in flagged if np.sign(axes[a]["scale"] - 1.0) == np.sign(sy - 1.0)]
    return bool(same and np.isfinite(sey) and abs(sy - 1.0) > max(MOTOR_YAW_CHANGE, MOTOR_YAW_SE * sey))


def yaw_scale(data, params: Mapping[str, float], vp: VehicleParams, t_split: float,
              t_split2: float) -> tuple[float, float]:
    """The yaw axis alone as :func:`inertia` reads it on ``vp``: (scale, standard error), NaN where it cannot."""
    setup = _flight(data, params, vp, t_split, t_split2)
    if setup is None:
        return math.nan, math.nan
    loop, idx, (every, *_) = setup
    R = residuals(loop, 2, data.w[idx, 2], data.w_sp[idx, 2], data.dt)
    return fit_scale(R, SCALES, every)


def _relative_sse(R: np.ndarray) -> list[float]:
    """Sum of squares over all windows at each grid value, over its minimum (the curve a report plots)."""
    sse = np.einsum("skn,skn->s", R, R)
    return [round(float(x), 5) for x in sse / max(float(sse.min()), 1e-300)]


def _gain(s: float, se: float) -> tuple[float, float]:
    """Authority per command over the model's (1 / scale) and its standard error."""
    if not (np.isfinite(s) and s > 0):
        return math.nan, math.nan
    return 1.0 / s, (se / (s * s) if np.isfinite(se) else math.nan)


#: the motors' time constants every window is simulated at [s] (log-spaced), and the extra command
#: delays the lag is compared with [s]
TAUS = np.exp(np.linspace(math.log(0.01), math.log(0.4), 41))
DELAYS = np.exp(np.linspace(math.log(0.002), math.log(0.1), 16))
#: a motor lag is reported when the rate loop reads it this far from the model's (relative, and
#: ``MIN_SE`` standard errors): the 12 PX4 SIH no-effect flights read 0.048-0.052 s for 0.05, the
#: inertia flights (one axis slower) 0.052-0.062 jointly; SIH_T_TAU 0.09 reads 0.088, 0.12 0.114-0.125
MIN_TAU_CHANGE = 0.30
#: and on every axis on its own (roll, pitch, yaw) at least this fraction of the joint change: the
#: motors act on every axis alike, an inertia on its own axis (Ixx x1.3: roll 0.062, yaw 0.052 s)
AXIS_AGREE = 0.5


def _axis_rms(loop: RateLoop, data, idx: np.ndarray) -> list[float]:
    """Each axis's residual RMS with the model as it is (the units :func:`_stacked` puts them in)."""
    out = []
    for ax in range(3):
        R0 = residuals(loop, ax, data.w[idx, ax], data.w_sp[idx, ax], data.dt, np.array([1.0]))[0]
        out.append(float(np.sqrt(np.mean(R0 ** 2))) or 1.0)
    return out


def _stacked(loop: RateLoop, field: str, values: np.ndarray, data, idx: np.ndarray,
             base: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """(V, K, 3 n) residuals of the three axes side by side, each in units of its own residual's RMS
    at the model's value ``base`` (:func:`_axis_rms`: the axes' gyro noise differs several-fold), for
    each value of the loop's ``field`` (``tau_s`` or ``command_delay_s``); and the per-axis (3, V) SSE."""
    per = []
    for ax in range(3):
        if field == "tau_s":
            R = residuals(loop, ax, data.w[idx, ax], data.w_sp[idx, ax], data.dt, taus=values)
        else:
            R = np.stack([residuals(dataclasses.replace(loop, **{field: v}), ax, data.w[idx, ax], data.w_sp[idx, ax],
                                    data.dt, np.array([1.0]))[0] for v in values])
        per.append(R)
    sse = np.array([np.einsum("vkn,vkn->v", R, R) for R in per])
    return np.concatenate([R / b for R, b in zip(per, base)], axis=-1), sse


def motor_lag(data, params: Mapping[str, float], vp: VehicleParams, t_split: float, t_split2: float) -> dict | None:
    """The motors' time constant PX4's rate loop reads (:func:`rate_loop` on the model ``vp``, driven by
    the logged rate setpoint), one for all three axes, and the same for an extra command delay instead.

    ``tau`` (all windows) with its clustered standard error, ``tau_fold1``/``tau_fold2`` (the folds as
    :func:`inertia`), each axis's own ``axis_tau``, both folds' held-out residual along its sensitivity
    at the model's lag and at each fold's lag (``heldout_before``/``heldout_after``, :func:`projected_folds`),
    both folds' held-out sum of squares of the lag and of the best delay (``heldout_sse``), and ``flagged``: the lag is far from the
    model's (``MIN_TAU_CHANGE``, ``MIN_SE``) on every axis the same way (``AXIS_AGREE``).  ``None``
    when the log is not PX4's, has no rate setpoint, or too few windows."""
    setup = _flight(data, params, vp, t_split, t_split2)
    if setup is None:
        return None
    loop, idx, (every, fit1, test1, fit2, test2) = setup
    base = _axis_rms(loop, data, idx)
    R, sse_ax = _stacked(loop, "tau_s", TAUS, data, idx, base)
    tau, se = fit_scale(R, TAUS, every)
    tau1, se1 = fit_scale(R, TAUS, fit1)
    tau2, se2 = fit_scale(R, TAUS, fit2)
    # held out: each fold's held-out windows at that fold's lag, pooled (:func:`projected_folds`, as :func:`inertia`)
    model = [(loop.tau_s, test1), (loop.tau_s, test2)]
    fits = [(tau1, test1), (tau2, test2)]
    b, tb = projected_folds(R, TAUS, model)
    a, ta = projected_folds(R, TAUS, fits)
    axis_tau = [float(TAUS[int(np.argmin(s))]) for s in sse_ax]
    # and per axis (each axis's columns of the stacked residual)
    m = R.shape[-1] // 3
    per_axis = {}
    for k, name in enumerate(AXES):
        Rk = R[:, :, k * m:(k + 1) * m]
        bk, _ = projected_folds(Rk, TAUS, model)
        ak, _ = projected_folds(Rk, TAUS, fits)
        per_axis[name] = {"before": bk, "after": ak,
                          "cut": 1.0 - ak / bk if np.isfinite(ak) and np.isfinite(bk) and bk > 0 else math.nan}
    # the delay instead of the lag, judged the same way (each fold's held-out sum of squares at its fit's value)
    D, _ = _stacked(loop, "command_delay_s", loop.command_delay_s + DELAYS, data, idx, base)
    k1, k2 = (int(np.argmin(np.einsum("vkn,vkn->v", D[:, f], D[:, f]))) for f in (fit1, fit2))
    j1, j2 = (int(np.argmin(np.abs(np.log(TAUS) - math.log(t)))) if np.isfinite(t) else 0 for t in (tau1, tau2))
    j0 = int(np.argmin(np.abs(np.log(TAUS) - math.log(loop.tau_s))))
    held = {"model": float(np.sum(R[j0, test1] ** 2) + np.sum(R[j0, test2] ** 2)),
            "lag": float(np.sum(R[j1, test1] ** 2) + np.sum(R[j2, test2] ** 2)),
            "delay": float(np.sum(D[k1, test1] ** 2) + np.sum(D[k2, test2] ** 2))}
    change = tau - loop.tau_s
    flagged = bool(np.isfinite(tau) and np.isfinite(se) and abs(change) > max(MIN_TAU_CHANGE * loop.tau_s, MIN_SE * se)
                   and all((x - loop.tau_s) * np.sign(change) >= AXIS_AGREE * abs(change) for x in axis_tau))
    return {"method": "rate_loop", "loop": loop.describe(), "windows": int(idx.shape[0]), "model_tau": loop.tau_s,
            "tau": tau, "se": se, "tau_fold1": tau1, "se_fold1": se1, "tau_fold2": tau2, "se_fold2": se2,
            "axis_tau": dict(zip(AXES, axis_tau)), "heldout_axes": per_axis, "heldout_before": b, "heldout_after": a,
            "heldout_t": abs(tb) if np.isfinite(tb) else math.nan, "heldout_t_after": abs(ta) if np.isfinite(ta) else math.nan,
            "delay_fold1": float(DELAYS[k1]), "heldout_sse": held, "flagged": flagged,
            "curve": {"taus": [round(float(x), 5) for x in TAUS],
                      **{a: [round(float(x), 5) for x in v / max(float(v.min()), 1e-300)] for a, v in zip(AXES, sse_ax)}}}


__all__ = ["AXES", "DELAYS", "MIN_CHANGE", "MIN_SE", "MIN_TAU_CHANGE", "MOTOR_YAW_CHANGE", "MOTOR_YAW_SE", "RateLoop",
           "SCALES", "TAUS", "WINDOW_S", "fit_scale", "inertia", "make_windows", "motor_lag", "motor_signature",
           "projected", "projected_folds", "rate_loop", "residuals", "simulate", "yaw_scale"]
