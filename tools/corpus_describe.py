"""Describe PX4 ULog files for the corpus list (docs/corpus_flights.csv): one JSON line per file.

    python tools/corpus_describe.py FILE.ulg ...

Reads only the log's own header, parameters and a few topics with pyulog: hardware and uuid, the
airframe (SYS_AUTOSTART, MAV_TYPE), rotor count (CA_ROTOR_COUNT where present, else the motor
outputs that move while armed), the PX4 release (``ver_sw_release`` decoded), the nav_state set,
the armed duration and whether the vehicle left the ground (land detector, else height change; a
vehicle whose tilt never moves, standard deviation under 0.2 deg, and whose height moves under 1.5 m
was held on a stand or tether: not airborne, whatever the land detector says).
It runs nothing of rotortwin.  An unreadable file is a line with its one-line error.
"""
from __future__ import annotations

import json
import sys

import numpy as np

NAV_NAMES = {0: "MANUAL", 1: "ALTCTL", 2: "POSCTL", 3: "AUTO_MISSION", 4: "AUTO_LOITER", 5: "AUTO_RTL",
             10: "ACRO", 12: "DESCEND", 13: "TERMINATION", 14: "OFFBOARD", 15: "STAB", 17: "AUTO_TAKEOFF",
             18: "AUTO_LAND", 19: "AUTO_FOLLOW", 20: "AUTO_PRECLAND", 21: "ORBIT", 22: "AUTO_VTOL_TAKEOFF"}


def px4_release(v: int | None) -> str:
    """``ver_sw_release`` is 0xAABBCCTT: major, minor, patch, type (255 release, <64 dev, <128 alpha...)."""
    if not v:
        return ""
    major, minor, patch, typ = (v >> 24) & 0xFF, (v >> 16) & 0xFF, (v >> 8) & 0xFF, v & 0xFF
    tag = "" if typ == 255 else ("-dev" if typ < 64 else "-alpha" if typ < 128 else "-beta" if typ < 192 else "-rc")
    return f"{major}.{minor}.{patch}{tag}"


def _topic(ulog, name, multi=0):
    for d in ulog.data_list:
        if d.name == name and d.multi_id == multi:
            return d.data
    return None


def _armed_span(ulog):
    st = _topic(ulog, "vehicle_status")
    if st is None or "arming_state" not in st:
        return None, None, st
    armed = st["arming_state"] == 2
    if not armed.any():
        return None, None, st
    t = st["timestamp"][armed]
    return int(t[0]), int(t[-1]), st


def _moving_outputs(ulog, t0, t1):
    """Motor outputs: channels that vary while armed and idle at the disarmed value (``PWM_DISARMED``,
    else below 1000 us) -- servos and RC passthrough channels rest at 1000-1500 us."""
    p = ulog.initial_parameters
    disarmed = float(p.get("PWM_DISARMED", p.get("PWM_MAIN_DISARM", p.get("PWM_MAIN_DIS1", 1000))))
    am = _topic(ulog, "actuator_motors")
    if am is not None:
        keys = [k for k in am if k.startswith("control[")]
        sel = (am["timestamp"] >= (t0 or 0)) & (am["timestamp"] <= (t1 or 2**63))
        moving = [k for k in keys if np.nanmax(np.abs(am[k][sel]), initial=0) > 0.05
                  and np.nanstd(am[k][sel]) > 1e-3] if sel.any() else []
        return len(moving), "actuator_motors"
    best = (0, True, "")  # (count, idles at the disarmed value, source): most channels win, then idling ones
    for multi in range(4):
        ao = _topic(ulog, "actuator_outputs", multi)
        if ao is None:
            continue
        sel = (ao["timestamp"] >= (t0 or 0)) & (ao["timestamp"] <= (t1 or 2**63))
        if not sel.any():
            continue
        varying = [k for k in ao if k.startswith("output[") and np.nanstd(ao[k][sel]) > 5
                   and np.nanmax(ao[k][sel]) > 1000]
        idling = [k for k in varying if np.nanmin(ao[k]) <= max(disarmed, 1000)]
        cand = (len(idling), True, f"actuator_outputs[{multi}]")
        # a log that starts armed (or ESCs idling above PWM_DISARMED) never shows the disarmed value:
        # then the channels that vary while armed count, when they all idle above it together
        if not idling and varying and min(np.nanmin(ao[k][sel]) for k in varying) > max(disarmed, 1000):
            cand = (len(varying), False, f"actuator_outputs[{multi}] (no disarmed idle in the log)")
        if cand[:2] > best[:2]:
            best = cand
    return best[0], best[2]


def _span(data, t0, t1):
    return (data["timestamp"] >= (t0 or 0)) & (data["timestamp"] <= (t1 or 2**63))


def _tilt_sd_deg(ulog, t0, t1):
    """Standard deviation of the tilt (deg) while armed; nan without vehicle_attitude."""
    q = _topic(ulog, "vehicle_attitude")
    if q is None or "q[1]" not in q or not _span(q, t0, t1).any():
        return float("nan")
    sel = _span(q, t0, t1)
    q1, q2 = q["q[1]"][sel], q["q[2]"][sel]
    return float(np.degrees(np.arccos(np.clip(1 - 2 * (q1 * q1 + q2 * q2), -1, 1))).std())


def _height_range_m(ulog, t0, t1):
    lp = _topic(ulog, "vehicle_local_position")
    if lp is None or "z" not in lp or not _span(lp, t0, t1).any():
        return float("nan")
    z = lp["z"][_span(lp, t0, t1)]
    return float(np.nanmax(z) - np.nanmin(z))


#: a vehicle whose tilt stays this still while armed (deg, standard deviation) and whose height moves
#: less than 1.5 m is held (a stand, a tether, weights): hand-flown and mission flights measured 0.46-15
#: deg, the held/bench runs 0.01-0.09 deg (docs/corpus.md, batch 4)
HELD_TILT_SD_DEG = 0.2


def _airborne(ulog, t0, t1):
    """Land detector (else a height change > 1.5 m) -- unless the vehicle was held still."""
    dz, tilt_sd = _height_range_m(ulog, t0, t1), _tilt_sd_deg(ulog, t0, t1)
    if tilt_sd < HELD_TILT_SD_DEG and not dz > 1.5:
        return False
    land = _topic(ulog, "vehicle_land_detected")
    if land is not None and "landed" in land:
        sel = _span(land, t0, t1)
        if sel.any() and (land["landed"][sel] == 0).any():
            return True
    return dz > 1.5


def describe(path: str) -> dict:
    from pyulog import ULog
    topics = ["vehicle_status", "actuator_motors", "actuator_outputs", "vehicle_land_detected",
              "vehicle_local_position", "vehicle_attitude"]
    u = ULog(path, topics, disable_str_exceptions=True)
    info, p = u.msg_info_dict, u.initial_parameters
    t0, t1, st = _armed_span(u)
    nav = sorted({int(x) for x in st["nav_state"][(st["timestamp"] >= (t0 or 0)) & (st["timestamp"] <= (t1 or 2**63))]}) \
        if st is not None and "nav_state" in st else []
    n_moving, source = _moving_outputs(u, t0, t1)
    rotors = int(p["CA_ROTOR_COUNT"]) if "CA_ROTOR_COUNT" in p else None
    # a MAV_TYPE that names a rotor count caps the moving outputs (servo/RC channels also move)
    n_moving = min(n_moving, {2: 4, 13: 6, 14: 8}.get(int(p.get("MAV_TYPE", -1)), n_moving))
    return {
        "file": path, "ver_hw": info.get("ver_hw", ""), "sys_uuid": str(info.get("sys_uuid", "")),
        "sys_name": info.get("sys_name", ""), "SYS_AUTOSTART": int(p.get("SYS_AUTOSTART", -1)),
        "MAV_TYPE": int(p.get("MAV_TYPE", -1)), "CA_ROTOR_COUNT": rotors, "moving_outputs": n_moving,
        "output_source": source, "px4": px4_release(info.get("ver_sw_release")),
        "ver_sw_branch": info.get("ver_sw_branch", ""),
        "modes": "+".join(NAV_NAMES.get(n, str(n)) for n in nav),
        "armed_s": round((t1 - t0) / 1e6, 1) if t0 else 0.0,
        "log_s": round((u.last_timestamp - u.start_timestamp) / 1e6, 1),
        "airborne": _airborne(u, t0, t1),
        "height_range_m": round(_height_range_m(u, t0, t1), 2), "tilt_sd_deg": round(_tilt_sd_deg(u, t0, t1), 2),
        "has_gps_vel": _topic(u, "vehicle_local_position") is not None,
    }


def main(argv: list[str]) -> int:
    for path in argv:
        try:
            print(json.dumps(describe(path)), flush=True)
        except Exception as exc:  # one line per unreadable file, the rest go on
            print(json.dumps({"file": path, "error": f"{type(exc).__name__}: {exc}"}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
