"""Confirmation flights: a mission plan that excites what a ``likely`` effect still lacks.

For each ``likely`` effect of a :func:`~twin_nodes.discovery.discover.discover` result, one plan
file in the format of ``missions/*.plan.yaml`` (schema: :mod:`twin_nodes.mavlink.mission`;
``rotortwin mission check`` accepts it; ``rotortwin mission upload`` flies it on PX4, ``rotortwin
simulate --plan`` in our simulator).  Plans only use what that schema has: waypoints relative to
home with per-item speed and stop/fly-through; the heading follows the path (PX4
``MPC_YAW_MODE 0``), so turns in place come from stop waypoints with a direction change.

Manoeuvres (each repeated until it supplies the missing blocks, with a margin):

``yaw_sweeps``
    short legs (4 m) at 2 m/s that reverse or turn 90 degrees at stop waypoints: every stop is a
    yaw turn in place (yaw moment, yaw inertia, and the yaw dynamics of lag and delay).
``rate_doublets``
    dashes at 6 m/s between stop waypoints (hard accelerations and stops: pitch) and a fly-through
    zigzag with sharp corners (lateral accelerations: roll): roll/pitch inertia, lag, delay.
``vertical_steps``
    stop waypoints above one point alternating between two heights 10 m apart: collective steps
    (mass, thrust, a weak motor, lag).
``low_hover``
    slow legs at 0.6-1 m above the ground and steps up to 3 m and back (ground effect).
``fast_legs``
    long legs at 8 m/s in four directions (drag, wind).
"""

from __future__ import annotations

import math
from pathlib import Path

from twin_nodes.base.io import atomic_write_text

#: blocks (0.5 s) of excitation one repetition of each manoeuvre supplies, conservatively
BLOCKS_PER_REP = {"yaw_sweeps": 2, "rate_doublets": 4, "vertical_steps": 4, "low_hover": 4, "fast_legs": 6}
MIN_REPS = {"yaw_sweeps": 12, "rate_doublets": 6, "vertical_steps": 4, "low_hover": 4, "fast_legs": 2}
MAX_REPS = 30
ALT_M = 10.0
#: effects whose signature lies at the rate loop's frequencies: on PX4 SIH flights (docs/prove_results.md,
#: "High-rate logging") a 50 Hz motor log could not tell a motor lag from a delay nor resolve roll/pitch
#: inertia; the same flights logged every 4 ms could
RATE_LOOP_EFFECTS = ("motor_time_constant", "actuator_delay", "inertia")
#: a motor log slower than this (s between samples) is too slow for them
RATE_LOOP_LOG_S = 0.01


def _reps(kind: str, missing: int | None) -> int:
    need = 2 * (missing or 0)  # a margin of two: the follow-up is judged on its own blocks
    return int(min(MAX_REPS, max(MIN_REPS[kind], math.ceil(need / BLOCKS_PER_REP[kind]))))


def _wp(n: float, e: float, alt: float, speed: float, through: bool = False) -> dict:
    return {"north_m": round(float(n), 2), "east_m": round(float(e), 2), "alt_m": round(float(alt), 2),
            "speed_m_s": float(speed), "fly_through": bool(through)}


def manoeuvre(kind: str, reps: int, origin: tuple[float, float] = (5.0, 0.0), alt: float = ALT_M) -> list[dict]:
    """Waypoints of one manoeuvre kind, starting and ending at ``origin`` (north, east) at ``alt``."""
    n0, e0 = origin
    out = [_wp(n0, e0, alt, 2.0)]
    if kind == "yaw_sweeps":
        # reverse, then turn 90 degrees: headings N, S, E, W, ... each stop a turn in place
        legs = [(4.0, 0.0), (0.0, 0.0), (0.0, 4.0), (0.0, 0.0)]
        for i in range(reps):
            dn, de = legs[i % 4]
            out.append(_wp(n0 + dn, e0 + de, alt, 2.0))
    elif kind == "rate_doublets":
        for i in range(reps):
            if i % 2 == 0:  # a dash out and back with hard stops: pitch doublets
                out += [_wp(n0 + 12.0, e0, alt, 6.0), _wp(n0, e0, alt, 6.0)]
            else:           # a fly-through zigzag: roll at every corner
                out += [_wp(n0 + 5.0, e0 + 5.0, alt, 6.0, True), _wp(n0 + 10.0, e0, alt, 6.0, True),
                        _wp(n0 + 15.0, e0 + 5.0, alt, 6.0, True), _wp(n0 + 20.0, e0, alt, 6.0),
                        _wp(n0, e0, alt, 6.0)]
    elif kind == "vertical_steps":
        for i in range(reps):
            out.append(_wp(n0, e0, alt + (10.0 if i % 2 == 0 else 0.0), 3.0))
        out.append(_wp(n0, e0, alt, 3.0))
    elif kind == "low_hover":
        for i in range(reps):
            out += [_wp(n0, e0, 1.0, 1.0), _wp(n0 + 6.0, e0, 0.6, 1.0), _wp(n0 + 6.0, e0, 3.0, 1.0),
                    _wp(n0, e0, 0.8, 1.0)]
        out.append(_wp(n0, e0, alt, 2.0))
    elif kind == "fast_legs":
        sq = [(60.0, 0.0), (60.0, 60.0), (0.0, 60.0), (0.0, 0.0)]
        for i in range(reps):
            for dn, de in sq:
                out.append(_wp(n0 + dn, e0 + de, alt, 8.0))
    else:
        raise ValueError(f"unknown manoeuvre {kind!r}")
    return out


def logging_advice(effect_name: str, motor_log_interval_s: float | None) -> str:
    """What to log on the confirmation flight ('' when the flight's logging was enough)."""
    if effect_name not in RATE_LOOP_EFFECTS or not motor_log_interval_s or motor_log_interval_s <= RATE_LOOP_LOG_S:
        return ""
    return (f"Log at the rate loop: this flight logged the motors every {1e3 * motor_log_interval_s:.0f} ms; "
            "log actuator_motors, vehicle_angular_velocity, vehicle_torque_setpoint, vehicle_thrust_setpoint "
            "and sensor_combined every 4 ms (PX4 SDLOG_PROFILE high-rate bit 4, e.g. SDLOG_PROFILE 17, or a "
            "logger_topics.txt), which separates a motor lag from a delay and resolves roll/pitch inertia.")


def plan_for(effect: dict, flight: str = "", motor_log_interval_s: float | None = None) -> dict:
    """The plan document (``{"mission": {...}}``) for one ``likely`` effect of a discover result;
    ``motor_log_interval_s``: how often the flight logged its motor commands (adds
    :func:`logging_advice` to the notes)."""
    ex = effect.get("excitation") or {}
    kinds = ex.get("plans") or ["rate_doublets"]
    missing = ex.get("blocks_missing")
    wps: list[dict] = []
    for kind in kinds:
        seg = manoeuvre(kind, _reps(kind, missing))
        wps += seg if not wps else seg[1:]
    pretty = ", ".join(f"{k}={v:.4g}" for k, v in effect.get("params", {}).items())
    notes = (f"confirmation flight for {effect['name']} ({pretty}), likely on {flight or 'the flight'}: "
             f"{effect.get('verdict_note', '')}. Manoeuvres: {', '.join(kinds)}. After flying it: "
             f"rotortwin discover {flight or 'FLIGHT'} --confirm FOLLOWUP.ulg")
    advice = logging_advice(effect["name"], motor_log_interval_s)
    if advice:
        notes += ". " + advice
    return {"mission": {"name": f"confirm_{effect['name']}", "speed_m_s": 3.0, "acceptance_radius_m": 1.0,
                        "fly_through": False, "rtl_after": True, "notes": notes, "waypoints": wps}}


def plan_yaml(doc: dict) -> str:
    """A plan document as YAML text, one waypoint per line (as the shipped plans are written)."""
    m = doc["mission"]
    lines = [f"# {m['notes']}",
             "# Waypoints are [north_m, east_m, alt_m above home] relative to home (the take-off point); the",
             "# heading follows the path (PX4 MPC_YAW_MODE 0), so each stop waypoint with a new direction is a",
             "# turn in place. Written by rotortwin discover --plan-dir; check with rotortwin mission check.",
             "mission:", f"  name: {m['name']}", f"  speed_m_s: {m['speed_m_s']}",
             f"  acceptance_radius_m: {m['acceptance_radius_m']}",
             f"  fly_through: {str(m['fly_through']).lower()}", f"  rtl_after: {str(m['rtl_after']).lower()}",
             "  waypoints:"]
    for w in m["waypoints"]:
        lines.append(f"    - {{north_m: {w['north_m']}, east_m: {w['east_m']}, alt_m: {w['alt_m']}, "
                     f"speed_m_s: {w['speed_m_s']}, fly_through: {str(w['fly_through']).lower()}}}")
    return "\n".join(lines) + "\n"


def write_plans(result: dict, folder: str | Path, flight: str = "") -> list[Path]:
    """One plan file per ``likely`` effect of ``result``; returns the paths written (the flight's
    motor log interval, ``result["method"]["motor_log_interval_s"]``, decides the logging advice)."""
    motor_log_interval_s = (result.get("method") or {}).get("motor_log_interval_s")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for e in result.get("effects", []):
        if e.get("verdict") != "likely":
            continue
        p = out / f"confirm_{e['name']}.plan.yaml"
        atomic_write_text(p, plan_yaml(plan_for(e, flight or str(result.get("log", "")), motor_log_interval_s)))
        paths.append(p)
    return paths


__all__ = ["RATE_LOOP_EFFECTS", "logging_advice", "manoeuvre", "plan_for", "plan_yaml", "write_plans"]
