"""Equation-error residuals: what the log measured minus what the model says the
logged motor commands produce, expressed as per-motor thrust errors.

The controller hides most model errors from position, but not from forces: the
accelerometer measures the specific force and the gyro the rotation, both of
which the model predicts from the motor commands alone.  For a parameter set
``vp`` (nominal vehicle + candidate effects) and every sample:

    r_F = m f_meas - F_model                 body force error   [N]   (FLU)
    r_M = J alpha_meas + w x J w - M_model   body moment error  [N m]

``[r_Fz, r_M]`` is mapped through the allocation pseudo-inverse to one thrust
error per rotor; rotor and horizontal errors are divided by the nominal
maximum rotor thrust, so every channel is in *fraction of full motor output*,
the unit of PX4's motor outputs and throttle.  Channels: ``motor1..N``,
``force_x``, ``force_y`` (horizontal force / (N T_max)).

All quantities are computed through :class:`~twin_nodes.physics.model.Multirotor`,
so any effect that plugs into the model is a discovery candidate with no
separate regression formula.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit

from twin_nodes.discovery.kernels import kernels
from twin_nodes.discovery.lowpass import lowpass
from twin_nodes.vehicle.geometry import allocation_matrix
from twin_nodes.base.errors import LogError
from twin_nodes.logs import time_sync
from twin_nodes.vehicle import px4_params
from twin_nodes.vehicle.params import VehicleParams
from twin_nodes.physics.core import I_MODE, I_N, I_TDN, I_TUP, I_WCMD, I_WMAX, I_WMIN, NX_BODY
from twin_nodes.physics.effects import Effect
from twin_nodes.physics.model import Multirotor

DEFAULT_RATE_HZ = 50.0
LOWPASS_HZ = 2.0


@dataclass
class EquationData:
    """A flight log prepared for equation-error identification (uniform grid, ROS frames)."""

    path: str
    t: np.ndarray                 # (T,) s since log start
    valid: np.ndarray             # (T,) bool: airborne, not on the ground, data finite
    p: np.ndarray                 # (T, 3) position ENU
    v: np.ndarray                 # (T, 3) velocity ENU
    q: np.ndarray                 # (T, 4) attitude wxyz FLU->ENU
    w: np.ndarray                 # (T, 3) body rates FLU
    alpha: np.ndarray             # (T, 3) angular acceleration FLU
    f: np.ndarray                 # (T, 3) specific force FLU
    u_fine: np.ndarray            # (T * up, N) commands on the fine grid (NaN stopped)
    up: int                       # fine-grid oversampling
    battery_v: np.ndarray         # (T,) V (NaN unknown)
    height: np.ndarray            # (T,) m above the take-off ground level
    motor_dt_s: float             # logging interval of the motor topic
    info: dict = field(default_factory=dict)
    #: (T, 3) the rate loop's setpoint, FLU rad/s (None: not logged); an instrument, never a residual
    w_sp: np.ndarray | None = None
    #: (T,) bool: where the attitude channels (moments, horizontal force) are usable, a subset of
    #: ``valid`` (the longer ground-contact pad after a lift-off, :func:`contact_pads`); None: ``valid``
    attitude_valid: np.ndarray | None = None
    #: (T,) bool: where the closed-loop twin is scored (:func:`scored_span`): as ``attitude_valid`` but not
    #: needing the horizontal position and velocity, which the twin's throttle and motors do not; None: that
    attitude_scored: np.ndarray | None = None
    #: what every candidate evaluation reuses (see :func:`model_rotor_states`, :func:`exogenous`,
    #: :func:`residual_channels`); derived from the fields above, never changes a result
    cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])

    @property
    def n(self) -> int:
        return len(self.t)

    @property
    def valid_attitude(self) -> np.ndarray:
        """The samples the moment and horizontal force channels are read on."""
        return self.valid if self.attitude_valid is None else self.attitude_valid


def _lowpass(x: np.ndarray, rate_hz: float, cutoff_hz: float) -> np.ndarray:
    """The zero-phase 2nd-order Butterworth low-pass along time: ``sosfiltfilt`` (lowpass.py: the same
    numbers, one compiled call)."""
    return lowpass(x, float(rate_hz), float(cutoff_hz))


def _fill_nan(x: np.ndarray) -> np.ndarray:
    """Linear fill of NaN gaps per column (for filtering only; the mask keeps them out)."""
    x = np.array(x, float, copy=True)
    if x.ndim == 1:
        x = x[:, None]
    idx = np.arange(len(x))
    for c in range(x.shape[1]):
        good = np.isfinite(x[:, c])
        if good.sum() >= 2:
            x[~good, c] = np.interp(idx[~good], idx[good], x[good, c])
        else:
            x[:, c] = 0.0
    return x


def _fine_commands(ms, lo: float, n: int, dt: float, oversample: int, command_hold_s: float
                   ) -> tuple[np.ndarray, float]:
    """The motor commands on a grid ``oversample`` times finer than the ``n``-sample grid from ``lo``:
    linear between logged samples, NaN (stopped) kept; and the motor logging interval."""
    step = dt / oversample
    t_fine = lo + np.arange(n * oversample) * step
    # the model holds u_fine[k] over its whole step [t_fine[k], t_fine[k] + step] (lag_states): read it at
    # the step's middle, where a held value equals the step's mean, and the command acting there was
    # logged command_hold_s earlier (read at the step's start it acts half a step, 1 ms, late)
    t_cmd = t_fine + 0.5 * step - command_hold_s
    u_fine = np.empty((len(t_fine), ms.values.shape[1]))
    for i in range(ms.values.shape[1]):
        col = ms.values[:, i]
        fin = np.isfinite(col)
        u_fine[:, i] = np.interp(t_cmd, ms.t_s[fin], col[fin]) if fin.sum() >= 2 else np.nan
        stopped = np.interp(t_cmd, ms.t_s, (~fin).astype(float)) > 0.5
        u_fine[stopped, i] = np.nan
    motor_dt = float(np.median(np.diff(ms.t_s))) if len(ms.t_s) > 1 else dt
    return u_fine, motor_dt


#: the refusal's field where the flight has 5 s to score but not 5 s with horizontal velocity to fit (``rotortwin
#: survey`` flies and scores the nominal there, as on a flight without GPS)
NO_HORIZONTAL_FIELD = "airborne samples with horizontal velocity"

#: the ground-contact pads (s): before a contact sample (touchdown transients, the 2 Hz low-pass's
#: spread of the normal force) and after one (a lift-off); the attitude (moment and horizontal force)
#: channels keep the long pad after a lift-off too, the vertical force only the short one
CONTACT_PAD_BEFORE_S = 0.5
CONTACT_PAD_AFTER_S = 0.5
THROTTLE_PAD_AFTER_S = 0.1
#: climbing away (m/s up, the contact test's speed): the vertical force's shorter pad after a contact
#: sample holds only there; a real vehicle spinning up on the ground can leave the contact test early
#: (S500: thrust 0.72 of the weight, its EKF height 0.10 m, supported, for 0.4 s more)
CLIMB_OUT_M_S = 0.3


def contact_pads(contact: np.ndarray, rate_hz: float, climbing: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The contact samples padded per channel: (vertical force, attitude).

    Both are padded by ``CONTACT_PAD_BEFORE_S`` before each contact sample.  After a contact sample
    (a lift-off) the vertical force keeps ``THROTTLE_PAD_AFTER_S`` only where the vehicle climbs away
    (``climbing``; None: everywhere): once it climbs, the normal force is gone, and a Crazyflie climbs
    through its whole reach of ground effect in 0.5 s.  The moment and horizontal force channels keep
    ``CONTACT_PAD_AFTER_S``: an attitude flattened on the ground (RotorPy) or a skid's friction is let
    go at the lift-off and settles after it."""
    c = np.asarray(contact, bool)
    cs = np.concatenate([[0], np.cumsum(c)])
    n = len(c)
    i = np.arange(n)

    def padded(before: float, after: float) -> np.ndarray:
        b, a = int(round(before * rate_hz)), int(round(after * rate_hz))
        lo, hi = np.maximum(i - a, 0), np.minimum(i + b + 1, n)
        return (cs[hi] - cs[lo]) > 0

    attitude = padded(CONTACT_PAD_BEFORE_S, CONTACT_PAD_AFTER_S)
    throttle = padded(CONTACT_PAD_BEFORE_S, THROTTLE_PAD_AFTER_S)
    if climbing is not None:
        throttle |= attitude & ~np.asarray(climbing, bool)
    return throttle, attitude


def _ground_contact(vp: VehicleParams, data: EquationData, height: np.ndarray, rate_hz: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The grid samples in ground contact, padded per channel (:func:`contact_pads`)."""
    model = Multirotor(vp)
    S = model_rotor_states(model, data)
    thrust = model.params.rotors.thrust_from_state(np.maximum(S, 0)).sum(1)
    weight = vp.mass_kg * vp.gravity_m_s2
    contact = (height < 0.5) & (np.linalg.norm(data.v, axis=1) < 0.3) & (thrust < 0.7 * weight)
    contact |= height < 0.05
    # sitting on the ground whatever the height estimate says (after touchdown PX4's EKF height can
    # read 1 m for seconds): far too little thrust to fly, yet the accelerometer reads a supported
    # vehicle, not a falling one
    contact |= (thrust < 0.6 * weight) & (vp.mass_kg * data.f[:, 2] - thrust > 0.3 * weight)
    return contact_pads(contact, rate_hz, data.v[:, 2] >= CLIMB_OUT_M_S)


def _stepped_hold(timing: px4_params.SensorTiming, log) -> px4_params.SensorTiming:
    """``timing`` where the log states its command hold; else, where the log stamps every motor and IMU sample
    on one fixed step (:func:`time_sync.stamp_step_s`), each command held over that step, half a step later
    than its stamp (RotorPy's writer before tim13 and our generator: 250 Hz commands held 4 ms, no rate stated)."""
    step = 0.0 if timing.command_hold_s else time_sync.stamp_step_s(
        log.require("motors").t_s, log.require("specific_force_flu").t_s)
    if not step:
        return timing
    return replace(timing, command_hold_s=0.5 * step, sources=timing.sources + (
        f"motor commands {0.5e3 * step:.2f} ms later (held for the {1e3 * step:g} ms step every stamp sits on)",))


def prepare(log, vp: VehicleParams, rate_hz: float = DEFAULT_RATE_HZ, oversample: int = 10) -> EquationData:
    """Resample what equation error needs onto one grid and mark the usable samples."""
    need = ["position_enu", "velocity_enu", "attitude_q", "motors", "specific_force_flu"]
    for name in need:
        log.require(name)
    rates_name = "body_rates_flu" if log.get("body_rates_flu") is not None else "gyro_flu"
    log.require(rates_name)
    t0, t1 = log.airborne_interval()
    if not t1 - t0 > 5.0:
        raise LogError(log.path, "vehicle_land_detected", f"expected at least 5 s airborne, got {t1 - t0:.1f} s")
    # start a little before take-off and end a little after landing: ground effect lives there
    lo = max(t0 - 2.0, 0.0)
    hi = min(t1 + 1.0, log.duration_s)
    names = need + [rates_name] + [n for n in ("battery_v", "height_agl") if log.get(n) is not None]
    t, d = log.resample(names, rate_hz, lo, hi)
    n = len(t)
    dt = 1.0 / rate_hz
    # the IMU and the body rates are often logged faster than this grid (PX4: sensor_combined every
    # 8 ms, 4 ms at high rate): average every sample into its grid step rather than pick one, which
    # keeps all of the sensor noise (PX4 SIH's accelerometer: 1.7 m/s^2 in y, gyro 0.14 rad/s in x)
    # PX4's logged signals come late against what the airframe did (the gyro low-pass, the IMU's
    # integration interval, the command held for a rate-loop step): each is re-timed by what the
    # log's own parameters say (px4_params.sensor_timing), else a fit would take PX4's sensor
    # latency for the motors' (on no-effect PX4 SIH flights: a 6-9 ms delay, tau_up 0.063 for 0.05)
    timing = _stepped_hold(px4_params.sensor_timing(log.params), log)
    late = {"specific_force_flu": timing.imu_average_s,
            rates_name: timing.gyro_filter_s if rates_name == "body_rates_flu" else timing.imu_average_s}
    for name in ("specific_force_flu", rates_name):
        s = log.require(name)
        d[name] = time_sync.sensor_to_grid(s.t_s, s.values, t, late[name], s.interp)
    # and low-pass the grid (the 2 Hz residual filter comes later)
    f = _lowpass(_fill_nan(d["specific_force_flu"]), rate_hz, min(10.0, 0.4 * rate_hz))
    # the body rates likewise: what the airframe does lies below 10 Hz (rotor lag, inertia), the rest
    # is gyro noise (PX4 SIH: 0.14 rad/s in roll) that would start every output-error window off
    w = _lowpass(_fill_nan(d[rates_name]), rate_hz, min(10.0, 0.4 * rate_hz))
    # Angular acceleration: central difference of the body rates; the 2 Hz low-pass every
    # residual goes through does the smoothing, identically on the model side (a smoothing
    # derivative here would shrink acceleration pulses and bias inertia up).  PX4's own
    # vehicle_angular_velocity.xyz_derivative is the D-term's filtered derivative: on the SIH
    # logs its roll axis even anti-correlates with the true moment, so it is not used.
    alpha = np.gradient(w, dt, axis=0)
    # commands on a fine grid: linear between logged samples, NaN (stopped) kept
    ms = log.require("motors")
    u_fine, motor_dt = _fine_commands(ms, lo, n, dt, oversample, timing.command_hold_s)
    p = d["position_enu"]
    # ground level: median height while landed before take-off (or the lowest airborne height)
    pre = (t < t0) & np.isfinite(p[:, 2])
    ground = float(np.median(p[pre, 2])) if pre.sum() > 5 else float(np.nanpercentile(p[:, 2], 1))
    height = p[:, 2] - ground
    if "height_agl" in d:
        # the distance sensor where it is valid: EKF height is too noisy near the ground
        agl = d["height_agl"].reshape(n)
        height = np.where(np.isfinite(agl), agl, height)
    batt = d["battery_v"].reshape(n) if "battery_v" in d else np.full(n, np.nan)
    finite_z = np.isfinite(p[:, 2]) & np.isfinite(d["attitude_q"]).all(1) & np.isfinite(w).all(1) & np.isfinite(f).all(1)
    finite = finite_z & np.isfinite(p[:, :2]).all(1) & np.isfinite(d["velocity_enu"]).all(1)
    u_grid = u_fine[::oversample][:n]
    armed = np.isfinite(u_grid).all(1)
    data = EquationData(path=log.path, t=t, valid=finite & armed, p=p, v=d["velocity_enu"], q=d["attitude_q"],
                        w=w, alpha=alpha, f=f, u_fine=u_fine, up=oversample, battery_v=batt, height=height,
                        motor_dt_s=motor_dt,
                        info={"airborne": (t0, t1), "ground_enu_z": ground, "timing": timing.describe()})
    # exclude ground contact: low, slow, and the model's thrust well below the weight
    contact, contact_attitude = _ground_contact(vp, data, height, rate_hz)
    data.attitude_valid = data.valid & ~contact_attitude
    data.attitude_scored = finite_z & armed & ~contact_attitude
    data.valid &= ~contact
    data.info["contact_samples"] = int(contact.sum())
    data.info["contact_samples_attitude"] = int(contact_attitude.sum())
    rs = log.get("setpoint_rates_flu")
    if rs is not None and len(rs.t_s) > 1:
        data.w_sp = rs.at(t)
    if data.valid.sum() < 5 * rate_hz:
        scored_s = float(data.attitude_scored.sum()) / rate_hz
        if scored_s >= 5.0:
            raise LogError(log.path, NO_HORIZONTAL_FIELD,
                           f"expected at least 5 s of usable airborne data, got {data.valid.sum() / rate_hz:.1f} s with "
                           f"horizontal velocity ({scored_s:.1f} s without it: GPS velocity valid in part of the flight)")
        raise LogError(log.path, "airborne samples", "expected at least 5 s of usable airborne data")
    return data


#: rotor-state series kept per flight (each (T, N), a few hundred kB); the fits of one candidate
#: revisit a handful of command paths, the other candidates share the nominal one
_ROTOR_CACHE_SIZE = 16
#: what of the packed vehicle ``P`` the command path reads (stepper.rotor_states: command_to_ref,
#: limit_ref and the lag); the command hooks' effect vectors are added to the key separately
_COMMAND_PATH_P = np.array([I_N, I_MODE, I_WMIN, I_WCMD, I_WMAX, I_TUP, I_TDN])


def _grid(data: EquationData, n: int, up: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Times and interpolated battery voltage of the (n samples, step/up) grid, once per flight."""
    key = ("grid", n, up)
    if key not in data.cache:
        t = data.t[0] + np.arange(n) * (data.dt / up)
        batt = (np.interp(t, data.t, _fill_nan(data.battery_v)[:, 0]) if np.isfinite(data.battery_v).any()
                else None)
        for a in (t, batt):
            if a is not None:
                a.flags.writeable = False
        data.cache[key] = (t, batt)
    return data.cache[key]


def exogenous(model: Multirotor, data: EquationData, n: int, up: int = 1) -> np.ndarray:
    """Exogenous inputs (battery voltage; wind from a wind effect) on the grid (n samples, step/up).
    On the residual's own grid (``up`` 1) a plain model's series (:func:`_plain_exogenous`) is made once per
    flight and copied (every candidate evaluation asks for it)."""
    plain = up == 1 and isinstance(getattr(data, "cache", None), dict) and _plain_exogenous(model)
    if plain and ("ext_plain", n) in data.cache:
        return data.cache[("ext_plain", n)].copy()
    t, batt = _grid(data, n, up)
    ext = model.exogenous(t, np.random.default_rng(0), None if batt is None else batt.copy())
    if plain:
        kept = ext.copy()
        kept.flags.writeable = False
        data.cache[("ext_plain", n)] = kept
    return ext


def _command_path_key(model: Multirotor, data: EquationData, delay_steps: int) -> tuple | None:
    """Everything the rotor-state integration reads besides the logged commands (the command
    path's entries of ``P`` and the delay), or None (do not cache) when an effect hooks into the
    command path (battery sag: its parameters change with every evaluation of its fit anyway)."""
    if not isinstance(getattr(data, "cache", None), dict):
        return None
    if any(e.command_kernel is not None for e in model.kernel_effects):
        return None
    return ("rotor", model.P[_COMMAND_PATH_P].tobytes(), int(delay_steps))


def _hooked_path_key(model: Multirotor, data: EquationData, delay_steps: int) -> tuple | None:
    """For a vehicle whose command path has effect hooks (battery sag): everything the hooked
    rotor-state kernel (``kernels.lag_states``) reads besides the logged commands and the exogenous
    series (by its digest, added in ``model_rotor_states``): the core's command-path entries of ``P``, the delay,
    the stepper module (its kind codes) and each command-hook effect's kind and parameter vector in table order.
    Most candidates leave all of these alone (a mass, a drag, an inertia), so the series is reused."""
    if not isinstance(getattr(data, "cache", None), dict):
        return None
    hooks = tuple((type(e).__name__, np.asarray(e.vector(), float).tobytes())
                  for e in model.kernel_effects if e.command_kernel is not None)
    return ("rotor_hooked", model._mod.__name__, model.P[_COMMAND_PATH_P].tobytes(), int(delay_steps), hooks)


def _keep(data: EquationData, key: tuple, value) -> None:
    """Store ``value`` under ``key`` in the flight's cache, at most ``_ROTOR_CACHE_SIZE`` of its kind."""
    old = [k for k in data.cache if isinstance(k, tuple) and k[0] == key[0]]
    if len(old) >= _ROTOR_CACHE_SIZE:
        del data.cache[old[0]]
    data.cache[key] = value


@njit(cache=True)
def lag_states(P, U, dt, delay_steps, s0, up, n_out):
    """Every ``up``-th rotor state (n_out, N) from commands U (T, N) on a grid of step dt: what
    the model's ``rotor_states`` kernel computes for a vehicle whose command path has no effect
    hooks (core.command_to_ref, limit_ref, the delay and the first-order lag, the same operations
    in the same order), in one loop with the vehicle's constants read once; the model's kernel
    goes through its generic hook machinery per sample and takes ~6x longer.  A test checks
    both agree bit for bit (tests/test_discovery_speed.py)."""
    n = int(P[I_N])
    nt = U.shape[0]
    S = np.empty((n_out, n))
    s = s0.copy()
    sref = np.empty(n)
    a_up = 1.0 - np.exp(-dt / P[I_TUP]) if P[I_TUP] > 1e-9 else 1.0
    a_dn = 1.0 - np.exp(-dt / P[I_TDN]) if P[I_TDN] > 1e-9 else 1.0
    mode0 = P[I_MODE] == 0.0
    wmin = P[I_WMIN]
    wcmd = P[I_WCMD]
    wmax = P[I_WMAX]
    for t in range(nt):
        if t % up == 0 and t // up < n_out:
            for i in range(n):
                S[t // up, i] = s[i]
        k = max(t - delay_steps, 0)
        for i in range(n):
            ui = U[k, i]
            if np.isnan(ui):  # stopped
                sref[i] = 0.0
                continue
            if ui < 0.0:
                ui = 0.0
            elif ui > 1.0:
                ui = 1.0
            sref[i] = min(wmin + ui * (wcmd - wmin), wmax) if mode0 else ui
        if mode0:  # limit_ref
            for i in range(n):
                sref[i] = min(sref[i], wmax)
        for i in range(n):
            e = sref[i] - s[i]
            s[i] += e * (a_up if e > 0.0 else a_dn)
    return S


def fine_commands(data: EquationData, nan_as_zero: bool = False) -> np.ndarray:
    """The logged commands on the fine grid, contiguous (NaN: stopped; ``nan_as_zero``: as 0),
    made once per flight (read-only)."""
    key = ("u_fine", nan_as_zero)
    if key not in data.cache:
        u = np.ascontiguousarray(data.u_fine, dtype=float)
        u = np.nan_to_num(u) if nan_as_zero else u.copy()
        u.flags.writeable = False
        data.cache[key] = u
    return data.cache[key]


def _plain_exogenous(model: Multirotor) -> bool:
    """No effect of ``model`` makes or changes an exogenous series (every effect but a wind): its series is
    then the logged battery voltage on the grid and the defaults, the same for every such model of a flight."""
    return all(type(e).exogenous is Effect.exogenous for e in model.effects)


def _digest(ext: np.ndarray) -> tuple:
    """An exogenous series' shape and 16-byte BLAKE2 digest (its part of the hooked rotor states' key)."""
    return ext.shape, hashlib.blake2b(ext.data, digest_size=16).digest()


def _plain_digest(model: Multirotor, data: EquationData, n: int, up: int) -> tuple:
    """:func:`_digest` of a plain model's exogenous series (:func:`_plain_exogenous`), made once per flight
    and grid: hashing the series on the command grid took ~1 ms per candidate evaluation."""
    key = ("ext_digest", n, up)
    if key not in data.cache:
        data.cache[key] = _digest(np.ascontiguousarray(exogenous(model, data, n, up)))
    return data.cache[key]


def _exogenous_key(model: Multirotor, n: int, up: int) -> tuple:
    """What a model's exogenous series on the (n, up) grid of a flight is made of besides the flight's own
    battery series: each effect that makes or changes it (its class, its parameters in name order, as bytes),
    in the model's order (the series' part of the hooked rotor states' key, for a model that is not
    plain).  The same key gives the same series (``exogenous`` draws from a fresh ``default_rng(0)``), so no
    series needs to be made and hashed (~1 ms on the command grid) before the cache is asked."""
    return ("ext_effects", n, up, tuple(
        (type(e), tuple(sorted(e.params)), np.array([e.params[k] for k in sorted(e.params)], float).tobytes())
        for e in model.effects if type(e).exogenous is not Effect.exogenous))


def model_rotor_states(model: Multirotor, data: EquationData) -> np.ndarray:
    """Rotor states on the grid, from the logged commands through the model's command path.

    Most candidates (mass, inertia, drag, a motor's efficiency...) leave the command path alone,
    so the series is kept per flight, keyed on what the integration reads (read-only array)."""
    up = data.up
    dt_f = data.dt / up
    delay_steps = int(round(model.command_delay_s / dt_f))
    key = _command_path_key(model, data, delay_steps)
    if key is not None and key in data.cache:
        return data.cache[key]
    s0 = np.zeros(model.n_rotors)
    if key is not None:
        # no command hooks: the command path is the core's alone (lag_states)
        u = fine_commands(data)
        S = lag_states(model.P, u, dt_f, delay_steps, s0, up, min(data.n, -(-len(u) // up)))
    else:
        plain = _plain_exogenous(model)
        hooked = _hooked_path_key(model, data, delay_steps)
        if hooked is not None:
            # the exogenous series by its digest (plain) or by what makes it (a wind), not a copy of it: on
            # the command grid (10x the residual's) 16 kept copies took a 60-min flight's discovery over its
            # 2 GB budget (bench_memory, 0.79 -> 1.26)
            hooked = hooked + (_plain_digest(model, data, len(data.u_fine), up) if plain
                               else _exogenous_key(model, len(data.u_fine), up))
        hit = data.cache.get(hooked) if hooked is not None else None
        if hit is not None:
            return hit
        ext = np.ascontiguousarray(exogenous(model, data, len(data.u_fine), up))
        u = fine_commands(data)
        S = kernels(model).lag_states(model.P, u, ext, dt_f, delay_steps, s0, up,
                                      min(data.n, -(-len(u) // up)))
        if hooked is not None:
            S.flags.writeable = False
            _keep(data, hooked, S)
    if key is not None:
        S.flags.writeable = False
        _keep(data, key, S)
    return S


def _body_states(data: EquationData) -> np.ndarray:
    """The logged body part of the model state (height for z, NaN as 0), once per flight."""
    if "body" not in data.cache:
        X = np.empty((data.n, NX_BODY))
        X[:, 0:3] = data.p
        X[:, 2] = data.height  # the model's z is height above the ground (ground contact, ground effect)
        X[:, 3:6] = data.v
        X[:, 6:10] = data.q
        X[:, 10:13] = data.w
        X = np.nan_to_num(X)
        X.flags.writeable = False
        data.cache["body"] = X
    return data.cache["body"]


def _measured(data: EquationData, vp: VehicleParams) -> tuple[np.ndarray, np.ndarray]:
    """Measured body force (m f) and moment (J alpha + w x J w) for this mass and inertia, each kept on what
    it reads (a mass candidate's evaluations share the moment)."""
    J = vp.inertia
    kf, km = ("measured_force", float(vp.mass_kg)), ("measured_moment", J.tobytes())
    if kf not in data.cache:
        _keep(data, kf, vp.mass_kg * data.f)
    if km not in data.cache:
        w = data.w
        _keep(data, km, data.alpha @ J.T + np.cross(w, w @ J.T))
    return data.cache[kf], data.cache[km]


def _sum_terms(arrays) -> np.ndarray:
    """``sum(arrays)`` (``0 + a0 + a1 + ...``) added into one new array: the same additions in the same order."""
    it = iter(arrays)
    total = next(it) + 0.0
    for a in it:
        np.add(total, a, out=total)
    return total


def _normalisation(data: EquationData, nominal: VehicleParams) -> tuple[np.ndarray, float, int]:
    key = ("norm", id(nominal))
    hit = data.cache.get(key)
    if hit is None or hit[0] is not nominal:
        hit = (nominal, allocation_matrix(nominal), nominal.rotors.thrust_at_full_command_n, nominal.rotors.count)
        data.cache[key] = hit
    return hit[1], hit[2], hit[3]


def residual_channels(data: EquationData, vp: VehicleParams, norm_params: VehicleParams | None = None,
                      extra_effects=(), lowpass_hz: float | None = LOWPASS_HZ) -> np.ndarray:
    """Residual channels (T, N + 2) in fraction of full motor output (see module doc).

    ``norm_params`` fixes the normalisation and allocation (the nominal vehicle), so
    candidates are compared in the same units.
    """
    model = Multirotor(vp, extra_effects)
    nominal = norm_params or vp
    S = model_rotor_states(model, data)
    X = np.empty((data.n, model.nx))
    X[:, :NX_BODY] = _body_states(data)
    X[:, NX_BODY:] = np.nan_to_num(S)
    ext = exogenous(model, data, data.n)
    terms = model.wrench_terms(X, ext)
    F = _sum_terms(v[0] for v in terms.values())
    M = _sum_terms(v[1] for v in terms.values())
    mF, mM = _measured(data, model.params)
    rF = mF - F
    rM = mM - M
    if data.attitude_valid is not None:
        # the attitude channels say nothing on the ground or just after a lift-off: zeroed before the
        # low-pass, so what the ground does to them (RotorPy's flattening) does not spread into the
        # samples the vertical force is read on
        off = ~data.attitude_valid
        rM[off] = 0.0
        rF[off, :2] = 0.0
    A, tmax, n_rot = _normalisation(data, nominal)
    per_motor = np.column_stack([rF[:, 2], rM]) @ A.T / tmax
    horiz = rF[:, :2] / (n_rot * tmax)
    R = np.column_stack([per_motor, horiz])
    R = np.where(np.isfinite(R), R, 0.0)
    if lowpass_hz:
        R = _lowpass(R, 1.0 / data.dt, lowpass_hz)
    return R


def channel_names(n_rotors: int) -> list[str]:
    return [f"motor{i + 1}" for i in range(n_rotors)] + ["force_x", "force_y"]


def mode_basis(rotors) -> np.ndarray:
    """(4, rotors) the collective (throttle), roll, pitch and yaw patterns of the per-motor errors: the
    effectiveness matrix's rows at unit norm (so the units stay fraction of full motor output)."""
    b = np.vstack([np.ones(rotors.count), np.array(rotors.y_flu_m), -np.array(rotors.x_flu_m),
                   -np.array(rotors.direction, float)])
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def modes(R: np.ndarray, vp: VehicleParams) -> tuple[np.ndarray, list[str]]:
    """Residual channels rotated into physical modes (:func:`mode_basis`), plus the horizontal force
    channels."""
    n = vp.rotors.count
    return (np.column_stack([R[:, :n] @ mode_basis(vp.rotors).T, R[:, n:]]),
            ["throttle", "roll", "pitch", "yaw", "force_x", "force_y"])
