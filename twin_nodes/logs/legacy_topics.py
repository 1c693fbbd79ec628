"""Older PX4 topic sets (PX4 1.8-1.13) read into :mod:`twin_nodes.logs.ulog_io`'s canonical series.

:func:`~twin_nodes.logs.ulog_io.read_ulog` picks a topic at a few places; where the newer one is
missing it asks this module for what older PX4 logged instead.  What PX4 logged per version was
read from PX4-Autopilot's own source (``src/modules/logger/logger.cpp`` (1.8-1.10) /
``logged_topics.cpp`` (1.11+), ``msg/*.msg``, ``ROMFS/px4fmu_common/init.d/rc.interface``,
``src/drivers/pwm_out/PWMOut.cpp``, ``src/lib/mixer/mixer_multirotor.cpp``); docs/real_logs.md has
the table, and how UAVCAN/DShot outputs and a mixer idle are told apart.  In short (default logger
profile):

========================== ========================================= ====================================
quantity                   PX4 1.8 - 1.9                              1.10 - 1.12 (1.13: both)
========================== ========================================= ====================================
body rates                 ``vehicle_attitude.rollspeed/pitchspeed/   ``vehicle_angular_velocity.xyz``
                           yawspeed`` (FRD, 30 ms)
collective / torque        ``actuator_controls_0.control[3]`` /       same; 1.12+ also
                           ``control[0..2]`` (normalised, 100 ms)     ``vehicle_thrust/torque_setpoint``
motors                     ``actuator_outputs`` PWM, 100 ms (10 Hz)   same; 1.13 ``actuator_motors``
                                                                      with control allocation
PWM limits                 ``PWM_MIN/MAX`` (1.8), per channel         ``PWM_MIN/MAX`` (``PWM_MAIN_MIN/MAX``
                           ``PWM_MAIN_MINn/MAXn`` when >= 0 (1.9+)    from 1.12), per channel when >= 0
                                                                      (1.13: and not 1000/2000)
position setpoint          1.8: ``vehicle_local_position_setpoint``   ``trajectory_setpoint`` (x,y,z,
                           (the controller's own setpoints);          vx,vy,vz; ``acceleration[3]``
                           1.9: ``trajectory_setpoint`` (no           feed-forward from 1.11; 1.13:
                           acceleration feed-forward until 1.11)      ``position[3]`` ...)
========================== ========================================= ====================================

PWM -> 0..1: PX4's multicopter mixer outputs ``u`` in [-1, 1] (``-1 + 2 * thrust`` with idle 0) and the
output driver writes ``pwm = min + (u + 1) / 2 * (max - min)`` (``pwm_limit``/``output_limit``), so the
normalised command is ``(pwm - min) / (max - min)`` with the log's own per-channel limits.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

__all__ = ["attitude_rates", "controls_torque", "pwm_limits", "setpoint_topic", "setpoint_arrays"]

#: PX4 defaults (``PWM_DEFAULT_MIN``/``MAX``) where a log sets no limit at all
PWM_DEFAULT = (1000.0, 2000.0)


def attitude_rates(att: Any) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Body rates (FRD, rad/s) from ``vehicle_attitude.rollspeed/pitchspeed/yawspeed`` (PX4 <= 1.9,
    before ``vehicle_angular_velocity``): ``(t_s, (n, 3) FRD, source)``, None when not logged."""
    if att is None or not att.has("rollspeed", "pitchspeed", "yawspeed"):
        return None
    w = att.cols(["rollspeed", "pitchspeed", "yawspeed"])
    return att.t_s, w, "vehicle_attitude.rollspeed,pitchspeed,yawspeed (FRD)"


def controls_torque(ac0: Any) -> tuple[np.ndarray, np.ndarray, str] | None:
    """The rate controller's normalised torque (FRD) from ``actuator_controls_0.control[0..2]``
    (PX4 <= 1.13, before ``vehicle_torque_setpoint``); None when not logged."""
    if ac0 is None or not ac0.has("control[0]", "control[1]", "control[2]"):
        return None
    return ac0.t_s, ac0.arr("control", 3), "actuator_controls_0.control[0..2] (FRD)"


def _param(params: dict[str, float], name: str) -> float | None:
    v = params.get(name)
    return float(v) if v is not None and np.isfinite(v) else None


def pwm_limits(params: dict[str, float], bank: str, chans: list[int]
               ) -> tuple[np.ndarray, np.ndarray, str]:
    """Each channel's PWM (min, max) [us] as PX4's mixer-era output driver set them, and how.

    ``chans`` are 0-based channels of the ``PWM_{bank}`` outputs.  Per channel, as PX4 does:
    ``PWM_{bank}_MINn``/``MAXn`` when set (>= 0; PX4 1.9-1.12 default them to -1 = unset,
    ``rc.interface``: ``pwm min -c n -p p:PWM_MAIN_MINn``; PX4 1.13's ``PWMOut`` also treats its new
    defaults 1000 / 2000 as unset), else the bank's ``PWM_{bank}_MIN``/``MAX`` (1.12+), else for MAIN
    the 1.8-1.9 ``PWM_MIN``/``PWM_MAX``, else 1000 / 2000 us."""
    era_113 = "SYS_CTRL_ALLOC" in params or any(k.startswith("PWM_MAIN_FUNC") for k in params)
    out = []
    for kind, i in (("MIN", 0), ("MAX", 1)):
        glob = _param(params, f"PWM_{bank}_{kind}")
        gname = f"PWM_{bank}_{kind}"
        if glob is None and bank == "MAIN":
            glob, gname = _param(params, f"PWM_{kind}"), f"PWM_{kind}"
        if glob is None or glob <= 0:
            glob, gname = PWM_DEFAULT[i], "PX4 default"
        vals, names = [], []
        for c in chans:
            v = _param(params, f"PWM_{bank}_{kind}{c + 1}")
            unset = v is None or v < 0 or (era_113 and v == PWM_DEFAULT[i])
            vals.append(glob if unset else v)
            names.append(gname if unset else f"PWM_{bank}_{kind}{c + 1}")
        out.append((np.array(vals), names))
    (lo, lo_n), (hi, hi_n) = out
    bad = ~(hi > lo)
    if bad.any():  # a corrupt pair: PX4 would not fly it either; keep the defaults there and say so
        lo, hi = np.where(bad, PWM_DEFAULT[0], lo), np.where(bad, PWM_DEFAULT[1], hi)
    srcs = list(dict.fromkeys(lo_n + hi_n))

    def fmt(v: np.ndarray) -> str:
        return f"{v[0]:.0f}" if np.all(v == v[0]) else "/".join(f"{x:.0f}" for x in v)

    how = (f"{', '.join(srcs)}: {fmt(lo)}-{fmt(hi)} us"
           + ("; max <= min on some channel: 1000-2000 us there" if bad.any() else ""))
    return lo, hi, how


def setpoint_topic(get: Callable[[str], Any]) -> tuple[Any, str] | tuple[None, None]:
    """The position-control setpoint topic: ``trajectory_setpoint`` (PX4 >= 1.9), else PX4 1.8's
    ``vehicle_local_position_setpoint`` (the position controller's own setpoints)."""
    for name in ("trajectory_setpoint", "vehicle_local_position_setpoint"):
        tp = get(name)
        if tp is not None and (tp.has("position[0]") or tp.has("x", "y", "z")):
            return tp, name
    return None, None


def _xyz(tp: Any, base: str, names: list[str]) -> np.ndarray | None:
    if tp.has(f"{base}[0]"):
        return tp.arr(base, 3)
    if tp.has(*names):
        return tp.cols(names)
    return None


def setpoint_arrays(tp: Any, name: str, lpos: Any, params: dict[str, float]
                    ) -> dict[str, tuple[np.ndarray, str]]:
    """Position / velocity / acceleration setpoints (NED) of the setpoint topic, as
    ``{"position"|"velocity"|"acceleration": (values (n, 3), source)}``.

    ``trajectory_setpoint``: ``position[3]`` (1.13+) or ``x,y,z``; ``velocity[3]`` or ``vx,vy,vz``
    (the feed-forward); ``acceleration[3]`` (1.11+, which ``PositionControl`` adds to the velocity
    loop's output).  PX4 1.9-1.10 log ``acc_x,acc_y,acc_z`` but their ``PositionControl`` only stores
    them (no acceleration feed-forward), so they are not read: the twin flies what PX4 flew.

    PX4 1.8's ``vehicle_local_position_setpoint`` holds the controller's own setpoints: ``vx..`` is
    the velocity loop's input ``(pos_sp - pos) * MPC_XY_P/MPC_Z_P + feed-forward`` and ``acc_x..``
    the thrust times g (``mc_pos_control_main.cpp``), so the feed-forward is taken back out of it
    with the log's position and gains, and the acceleration is not read."""
    out: dict[str, tuple[np.ndarray, str]] = {}
    pos = _xyz(tp, "position", ["x", "y", "z"])
    vel = _xyz(tp, "velocity", ["vx", "vy", "vz"])
    if pos is not None:
        out["position"] = (pos, f"{name} (NED)")
    if name == "trajectory_setpoint":
        if vel is not None:
            out["velocity"] = (vel, f"{name} (NED)")
        acc = tp.arr("acceleration", 3) if tp.has("acceleration[0]") else None
        if acc is not None:
            out["acceleration"] = (acc, f"{name}.acceleration (NED)")
        return out
    if vel is None:
        return out
    kxy, kz = _param(params, "MPC_XY_P"), _param(params, "MPC_Z_P")
    if pos is None or lpos is None or not lpos.has("x", "y", "z") or kxy is None or kz is None:
        return out  # no way to separate the feed-forward: fly the position setpoint alone
    from twin_nodes.logs import time_sync

    p_real = time_sync.interp_to(lpos.t_s, lpos.cols(["x", "y", "z"]), tp.t_s, kind="linear")
    # an axis without a position setpoint (NaN: AUTO land's descent at MPC_LAND_SPEED, the sticks in
    # POSCTL/ALTCTL) is velocity-controlled: its vx..vz is the setpoint itself, no position term to take out
    term = (pos - p_real) * np.array([kxy, kxy, kz])
    ff = vel - np.where(np.isfinite(pos), term, 0.0)
    out["velocity"] = (ff, f"{name}.vx,vy,vz - (x,y,z - position) * MPC_XY_P/MPC_Z_P "
                           "(the feed-forward, NED; as logged on axes without a position setpoint)")
    return out


#: canonical series -> the PX4 fields it is read from, newest first (for the one-line error when a
#: log has none of them)
PX4_SOURCES: dict[str, str] = {
    "position_enu": "vehicle_local_position.x,y,z",
    "velocity_enu": "vehicle_local_position.vx,vy,vz",
    "attitude_q": "vehicle_attitude.q",
    "body_rates_flu": "vehicle_angular_velocity.xyz (PX4 >= 1.10) or vehicle_attitude.rollspeed,pitchspeed,"
                      "yawspeed (PX4 <= 1.9)",
    "motors": "actuator_motors.control (PX4 >= 1.13 with control allocation) or actuator_outputs.output "
              "(PWM, motor channels moving while armed)",
    "throttle": ("vehicle_thrust_setpoint.xyz[2] (PX4 >= 1.12) or actuator_controls_0.control[3], else "
                 "vehicle_rates_setpoint.thrust (PX4 1.8-1.9, MC_BAT_SCALE_EN 0)"),
    "torque_setpoint_flu": "vehicle_torque_setpoint.xyz (PX4 >= 1.12) or actuator_controls_0.control[0..2]",
    "setpoint_position_enu": "trajectory_setpoint.position or .x,y,z (PX4 >= 1.9) or "
                             "vehicle_local_position_setpoint.x,y,z (PX4 1.8)",
    "setpoint_velocity_enu": "trajectory_setpoint.velocity or .vx,vy,vz (PX4 >= 1.9) or "
                             "vehicle_local_position_setpoint.vx,vy,vz with MPC_XY_P/MPC_Z_P (PX4 1.8)",
    "nav_state": "vehicle_status.nav_state",
    "armed": "vehicle_status.arming_state",
    "landed": "vehicle_land_detected.landed",
    "battery_v": "battery_status.voltage_v",
    "gyro_flu": "sensor_combined.gyro_rad",
    "specific_force_flu": "sensor_combined.accelerometer_m_s2",
}


#: UAVCAN ESC raw command full scale (``uavcan::equipment::esc::RawCommand.cmd``, 14 bit): PX4 1.9 writes
#: ``(u + 1) / 2 * 8191`` into actuator_outputs, 1.11+ its mixer output between 0 (1 with
#: ``UAVCAN_ESC_IDLT``) and 8191; 65535 = disarmed (``DISARMED_OUTPUT_VALUE``)
UAVCAN_RAW_MAX = 8191.0
#: DShot throttle full scale (``DSHOT_MAX_THROTTLE``; 0 = disarmed, minimum ``DSHOT_MIN`` x 1999, >= 1)
DSHOT_MAX = 1999.0
#: no PWM output is below this while armed (``PWM_LOWEST_MIN`` 90 us is a servo's; motor minimums are
#: 900+): channels of a PWM bank must stay above it, DShot/UAVCAN channels need not
PWM_ARMED_FLOOR = 800.0


def output_protocol(params: dict[str, float]) -> str:
    """``'uavcan'`` when UAVCAN ESCs are enabled (``UAVCAN_ENABLE`` >= 3), ``'dshot'`` when DShot is
    configured (``DSHOT_CONFIG`` > 0, PX4 1.10-1.12; a ``PWM_*_TIMn`` of -5..-2, 1.13+), else ``'pwm'``."""
    if (_param(params, "UAVCAN_ENABLE") or 0) >= 3:
        return "uavcan"
    tim = [v for k, v in params.items() if k.startswith(("PWM_MAIN_TIM", "PWM_AUX_TIM")) and np.isfinite(v)]
    if (_param(params, "DSHOT_CONFIG") or 0) > 0 or any(-5 <= v <= -2 for v in tim):
        return "dshot"
    return "pwm"


#: PX4's tap_esc driver (Yuneec Typhoon H480, ATL Mantis EDU): ``drv_tap_esc.h`` RPMMIN 1200, RPMMAX 1900,
#: RPMSTOPPED = RPMMIN - 10; the mixer's 0..1 is written as 1200..1900 in ``actuator_outputs``
TAP_ESC_RANGE = (1200.0, 1900.0)
TAP_ESC_STOPPED = 1190.0
#: airframes built on tap_esc boards (TAP_V2 H480 6021, Mantis EDU 4061): their logs carry no PWM limits
TAP_ESC_AIRFRAMES = (4061, 6021)


def tap_esc(params: dict[str, float], disarmed: np.ndarray) -> str | None:
    """Why this log's motor outputs are tap_esc's (``TAP_ESC_RANGE``), or None: no PWM limit parameter in
    the log and either the channels rest at RPMSTOPPED 1190 while disarmed (``disarmed``: their values
    then, any shape), the tap_esc parameters ``ESC_FW_VER``/``ESC_BL_VER`` or a tap_esc airframe."""
    if any(k.startswith(("PWM_MIN", "PWM_MAX", "PWM_MAIN_MIN", "PWM_MAIN_MAX")) for k in params):
        return None
    d = disarmed[np.isfinite(disarmed)]
    if d.size and np.mean(np.abs(d - TAP_ESC_STOPPED) < 0.5) > 0.5:
        return "outputs rest at tap_esc's RPMSTOPPED 1190 while disarmed"
    if "ESC_FW_VER" in params or "ESC_BL_VER" in params:
        return "tap_esc parameters ESC_FW_VER/ESC_BL_VER"
    a = _param(params, "SYS_AUTOSTART")
    if a is not None and int(a) in TAP_ESC_AIRFRAMES:
        return f"SYS_AUTOSTART {int(a)} is a tap_esc airframe"
    return None


def disarmed_pwm(params: dict[str, float], bank: str, n: int = 16) -> tuple[np.ndarray, str]:
    """Each of ``n`` channels' disarmed PWM [us] as PX4's mixer-era driver writes it (``pwm_limit``: INIT and
    OFF states), NaN where the log does not say, and the names used: ``PWM_{bank}_DISn`` when set (>= 0),
    else the bank's ``PWM_{bank}_DISARM`` (1.12-1.13) or ``PWM_{bank}_DISARMED`` (AUX, 1.8-1.11), else for
    MAIN ``PWM_DISARMED`` (1.8-1.11)."""
    names = [f"PWM_{bank}_DISARM", f"PWM_{bank}_DISARMED"] + (["PWM_DISARMED"] if bank == "MAIN" else [])
    glob, gname = next(((v, k) for k in names if (v := _param(params, k)) is not None and v >= 0), (np.nan, ""))
    out, used = [], set()
    for c in range(n):
        v = _param(params, f"PWM_{bank}_DIS{c + 1}")
        if v is not None and v >= 0:
            out.append(v)
            used.add(f"PWM_{bank}_DISn")
        else:
            out.append(glob)
            if gname:
                used.add(gname)
    return np.array(out, float), "/".join(sorted(used))


def armed_floor(params: dict[str, float]) -> float:
    """The lowest armed value a motor channel may have in this log's outputs (see PWM_ARMED_FLOOR)."""
    return PWM_ARMED_FLOOR if output_protocol(params) == "pwm" else 1.0


def output_limits(params: dict[str, float], bank: str, chans: list[int], armed: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, str]:
    """Each motor channel's (value at zero thrust, value at full thrust) in ``actuator_outputs`` units and
    how, for the mixer era (no output functions): PWM per :func:`pwm_limits`; UAVCAN raw commands
    (values above PWM's range while UAVCAN ESCs are enabled) 0..8191, or ``UAVCAN_EC_MINn/MAXn``;
    DShot (values below PWM's range while DShot is configured) ``max(1, DSHOT_MIN x 1999)``..1999.
    ``armed``: the channels' values while armed, (n, len(chans))."""
    proto = output_protocol(params)
    finite = armed[np.isfinite(armed)]
    top = float(finite.max()) if finite.size else 0.0
    low = float(finite.min()) if finite.size else PWM_ARMED_FLOOR
    k = len(chans)
    if proto == "uavcan" and top > 2500.0:
        lo = np.array([_param(params, f"UAVCAN_EC_MIN{c + 1}") or 0.0 for c in chans])
        hi = np.array([_param(params, f"UAVCAN_EC_MAX{c + 1}") or UAVCAN_RAW_MAX for c in chans])
        return lo, hi, f"UAVCAN ESC raw commands {lo.min():.0f}-{hi.max():.0f} (UAVCAN_ENABLE >= 3)"
    if proto == "dshot" and low < PWM_ARMED_FLOOR:
        dmin = _param(params, "DSHOT_MIN")
        lo = float(np.clip(int((dmin or 0.0) * DSHOT_MAX), 1.0, DSHOT_MAX))  # PX4 casts to int
        return (np.full(k, lo), np.full(k, DSHOT_MAX),
                f"DShot throttle {lo:.0f}-{DSHOT_MAX:.0f} (DSHOT_MIN {dmin if dmin is not None else 'unset'})")
    return pwm_limits(params, bank, chans)


#: share of armed samples above a channel's PWM maximum that shows the outputs were not clamped by it
ABOVE_MAX_FRACTION = 0.002


def not_driver_scaled(armed: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> str | None:
    """Why motor outputs were not written by PX4's PWM driver with the limits ``lo``..``hi`` (per channel,
    us), or None.  PX4's ``pwm_limit_calc`` clamps every armed output to ``[min_pwm, max_pwm]``, so a
    channel above its maximum (by more than 1 us, on at least ABOVE_MAX_FRACTION of the armed samples) was
    scaled by something else: a module that publishes ``actuator_outputs`` itself (a second publisher, see
    ``ulog_io._output_publishers``).  When every armed value then lies within PX4's default 1000..2000 us
    the outputs are read on that scale.  ``armed``: (n, channels) armed values."""
    a = np.asarray(armed, float)
    if a.size == 0:
        return None
    with np.errstate(invalid="ignore"):
        above = np.nanmean(a > hi[None, :] + 1.0, axis=0)
    fin = a[np.isfinite(a)]
    if not np.any(above >= ABOVE_MAX_FRACTION) or fin.size == 0:
        return None
    if fin.min() < PWM_DEFAULT[0] - 1.0 or fin.max() > PWM_DEFAULT[1] + 1.0:
        return None
    return (f"armed outputs above the PWM maximum {hi.max():.0f} us on up to {100 * above.max():.1f} % of "
            f"samples (PX4's driver clamps there): read on PX4's default {PWM_DEFAULT[0]:.0f}-"
            f"{PWM_DEFAULT[1]:.0f} us")


def mixer_idle(motors: Any, throttle: Any, airborne: list[tuple[float, float]]) -> tuple[float, str] | None:
    """The idle speed of a PX4 1.8-1.13 multicopter mixer file (the ``R:`` line's last number), found in
    the log: that mixer writes ``idle + (1 - idle) x out`` (``mixer_multirotor.cpp``: ``_idle_speed +
    outputs[i] * (1 - _idle_speed)``), so the mean motor command is ``idle + (1 - idle) x throttle``
    where nothing saturates.  Stock mixers have idle 0 (PWM_MIN gives the idle), and then the fit is
    0.000/1.000 on every shared log; a custom one (e.g. UAVCAN ESCs) shows here.  Returns
    ``(idle, how)`` when the fit is clear (intercept > 0.05, intercept + slope within 0.03 of 1,
    residual < 0.02 over a throttle range >= 0.1), else None."""
    t = motors.t_s
    inside = np.zeros(t.size, bool)
    for a, b in airborne:
        inside |= (t > a + 2.0) & (t < b - 2.0)
    if inside.sum() < 50:
        return None
    u = motors.values[inside]
    x = throttle.at(t[inside])[:, 0]
    ok = np.all(np.isfinite(u), 1) & np.isfinite(x) & (u.max(1, initial=0) < 0.99) & (u.min(1, initial=1) > 0.01)
    if ok.sum() < 50 or np.ptp(x[ok]) < 0.1:
        return None
    A = np.column_stack([np.ones(ok.sum()), x[ok]])
    y = u[ok].mean(1)
    (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = float(np.std(y - A @ [a, b]))
    if a > 0.05 and abs(a + b - 1.0) < 0.03 and resid < 0.02:
        return float(a), (f"mixer idle {a:.3f} undone (mean motor = {a:.3f} + {b:.3f} x throttle, "
                          f"residual {resid:.4f}, {int(ok.sum())} samples)")
    return None
