"""Fly PX4 SIH (real PX4 firmware with its built-in simulator) with SIH parameters changed, and keep each
flight as a prove flight: ``<out>/<id>/{flight.ulg, truth.json, MANIFEST.md}``.

The setup is the one ``missions/sih_effects/manifest.yaml`` describes (and the flights of
``../shared/flightlogs/sitl_effects`` were flown with): airframe 10040 ``sihsim_quadx``, headless, lockstep at
``PX4_SIM_SPEED_FACTOR``, the manifest's ``PX4_PARAM_*`` plus the flight's ``PX4_PARAM_SIH_<NAME>=<value>``,
an empty working directory per flight with ``etc/logging/logger_topics.txt`` written from the manifest's topic
list, and the ground-station steps of :mod:`twin_nodes.mavlink.mission` (upload with RTL after, current item 0,
arm, start, wait for the disarm after landing).  Afterwards every ULog 'P' and 'Q' message whose parameter name
starts with ``SIH_`` is removed (:func:`scrub_ulog`), so the truth cannot be read from the file; ``truth.json``
holds it (the format of ``../shared/flightlogs/sitl_effects/eNN/truth.json``).

Used by ``launch_scripts/fly_sih.sh`` (``python -m twin_nodes.mavlink.sih_flight``); needs a PX4-Autopilot tree
built with ``make px4_sitl_default``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from twin_nodes.base.errors import ParamsError, TwinError

REPO = Path(__file__).resolve().parents[2]
MANIFEST = REPO / "missions" / "sih_effects" / "manifest.yaml"

#: PX4's SIH defaults at the manifest's commit (src/modules/simulation/simulator_sih/sih_params.c)
SIH_DEFAULTS = {"SIH_MASS": 1.0, "SIH_IXX": 0.025, "SIH_IYY": 0.025, "SIH_IZZ": 0.030, "SIH_T_MAX": 5.0,
                "SIH_Q_MAX": 0.1, "SIH_L_ROLL": 0.2, "SIH_L_PITCH": 0.2, "SIH_KDV": 1.0, "SIH_KDW": 0.025,
                "SIH_T_TAU": 0.05}
#: parameters of missions/sih_effects/px4_sih_weak_motor_com.patch (not in stock PX4: a flight that sets one needs
#: the patched build): one weaker motor (PX4 order 1..4, its thrust and torque factor) and a centre of mass off
#: the rotors' centre (FRD body x forward, y right)
SIH_PATCHED = {"SIH_MOT_WEAK": 0, "SIH_MOT_EFF": 1.0, "SIH_CG_X": 0.0, "SIH_CG_Y": 0.0}
SIH_DEFAULTS.update(SIH_PATCHED)
#: accepted values of those: (low, high, integer)
_PATCHED_RANGE = {"SIH_MOT_WEAK": (1, 4, True), "SIH_MOT_EFF": (0.1, 1.0, False), "SIH_CG_X": (-0.1, 0.1, False),
                  "SIH_CG_Y": (-0.1, 0.1, False)}
ULOG_MAGIC = b"ULog\x01\x12\x35"


# --------------------------------------------------------------------------- the manifest


def load_manifest(path: str | Path = MANIFEST) -> dict:
    """The SIH manifest, checked for what flying needs (one-line errors naming file and field)."""
    from twin_nodes.base.yamlio import read_yaml_file

    p = str(path)
    doc = read_yaml_file(p, "SIH flights manifest")
    px4 = doc.get("px4") if isinstance(doc, dict) else None
    if not isinstance(px4, dict):
        raise ParamsError(p, "px4", "missing: expected a mapping (commit, environment, logging)")
    env = px4.get("environment")
    if not isinstance(env, dict) or "PX4_SYS_AUTOSTART" not in env:
        raise ParamsError(p, "px4.environment", "expected a mapping with PX4_SYS_AUTOSTART etc.")
    topics = (px4.get("logging") or {}).get("topics_interval_ms")
    if not isinstance(topics, dict) or not topics:
        raise ParamsError(p, "px4.logging.topics_interval_ms", "expected a mapping topic: interval_ms")
    for k, v in topics.items():
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ParamsError(p, f"px4.logging.topics_interval_ms.{k}", f"expected an integer >= 0, got {v!r}")
    profiles = px4["logging"].get("profiles") or {}
    if not isinstance(profiles, dict):
        raise ParamsError(p, "px4.logging.profiles", "expected a mapping name: {topics_interval_ms: ...}")
    for name, prof in profiles.items():
        over = prof.get("topics_interval_ms") if isinstance(prof, dict) else None
        if not isinstance(over, dict) or not over:
            raise ParamsError(p, f"px4.logging.profiles.{name}.topics_interval_ms", "expected a mapping topic: interval_ms")
        for k, v in over.items():
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ParamsError(p, f"px4.logging.profiles.{name}.topics_interval_ms.{k}",
                                  f"expected an integer >= 0, got {v!r}")
    for key in ("missions", "flights"):
        if not isinstance(doc.get(key), dict):
            raise ParamsError(p, key, "expected a mapping")
    doc["_path"] = p
    return doc


def logging_topics(manifest: dict, profile: str | None = None) -> dict[str, int]:
    """``{topic: interval_ms}`` of the manifest's default logging (``profile`` None or ``"default"``) or of a named
    profile of ``px4.logging.profiles`` (its ``topics_interval_ms`` replace those entries of the default list)."""
    topics = dict(manifest["px4"]["logging"]["topics_interval_ms"])
    if profile in (None, "default"):
        return topics
    profiles = manifest["px4"]["logging"].get("profiles") or {}
    if profile not in profiles:
        raise ParamsError(manifest["_path"], f"px4.logging.profiles.{profile}",
                          f"no such logging profile (known: {', '.join(['default', *profiles])})")
    topics.update(profiles[profile]["topics_interval_ms"])
    return topics


def logger_topics_text(manifest: dict, profile: str | None = None) -> str:
    """``etc/logging/logger_topics.txt``: one ``<topic> <interval_ms> 0`` line per topic of the logging profile."""
    name = profile or "default"
    lines = [(f"# <topic> [interval_ms]; interval 0 = every update (written from missions/sih_effects/manifest.yaml, "
              f"logging profile {name})")]
    lines += [f"{k} {int(v)} 0" for k, v in logging_topics(manifest, profile).items()]
    return "\n".join(lines) + "\n"


def mission_plan_path(manifest: dict, mission: str) -> Path:
    """A mission id of the manifest (``M3``) or a plan file path -> the plan file."""
    m = manifest["missions"].get(mission)
    if m is None:
        p = Path(mission)
        if p.is_file():
            return p
        raise ParamsError(manifest["_path"], f"missions.{mission}",
                          f"no such mission (known: {', '.join(manifest['missions'])}) and no such plan file")
    if not isinstance(m, dict) or not m.get("plan_file"):
        raise ParamsError(manifest["_path"], f"missions.{mission}.plan_file", "missing: expected a plan file path")
    p = REPO / m["plan_file"]
    if not p.is_file():
        raise ParamsError(manifest["_path"], f"missions.{mission}.plan_file", f"{p}: file not found")
    return p


def parse_sih(items: list[str] | dict | None, where: str = "--sih") -> dict[str, float]:
    """``["SIH_Q_MAX=0.16"]`` or ``{SIH_Q_MAX: [0.1, 0.16]}`` (the manifest's form) -> ``{name: value}``."""
    out: dict[str, float] = {}
    if isinstance(items, dict):
        pairs = [(k, v[-1] if isinstance(v, (list, tuple)) else v) for k, v in items.items()]
    else:
        pairs = []
        for it in items or ():
            if "=" not in it:
                raise TwinError(f"{where}: {it!r}: expected NAME=VALUE, e.g. SIH_Q_MAX=0.16")
            k, v = it.split("=", 1)
            pairs.append((k.strip(), v.strip()))
    for k, v in pairs:
        if k not in SIH_DEFAULTS:
            raise TwinError(f"{where}: {k}: expected one of {', '.join(SIH_DEFAULTS)}")
        try:
            x = float(v)
        except (TypeError, ValueError):
            x = math.nan
        if k in _PATCHED_RANGE:
            lo, hi, integer = _PATCHED_RANGE[k]
            if not (math.isfinite(x) and lo <= x <= hi and (not integer or x == int(x))):
                raise TwinError(f"{where}: {k}: expected {'an integer' if integer else 'a number'} in "
                                f"[{lo:g}, {hi:g}] (patched PX4 SIH), got {v!r}")
        elif not math.isfinite(x) or x <= 0.0:
            raise TwinError(f"{where}: {k}: expected a positive number, got {v!r}")
        out[k] = x
    if ("SIH_MOT_WEAK" in out) != ("SIH_MOT_EFF" in out):
        raise TwinError(f"{where}: SIH_MOT_WEAK and SIH_MOT_EFF: expected both (which motor and its factor)")
    return out


def truth_effects(sih: dict[str, float]) -> list[dict]:
    """The change in physical units, as ``../shared/flightlogs/sitl_effects/eNN/truth.json`` names it."""
    if not sih:
        return [{"name": "none", "params": {}}]
    names = set(sih)
    t_max = sih.get("SIH_T_MAX", SIH_DEFAULTS["SIH_T_MAX"])
    if names == {"SIH_MASS"}:
        return [{"name": "mass", "params": {"mass": sih["SIH_MASS"]}}]
    if names == {"SIH_T_MAX"}:
        return [{"name": "thrust_coefficient", "params": {"kt_scale": t_max / SIH_DEFAULTS["SIH_T_MAX"],
                                                          "t_max_n": t_max}}]
    if names == {"SIH_Q_MAX"}:
        return [{"name": "yaw_moment", "params": {"km": sih["SIH_Q_MAX"] / t_max, "q_max_nm": sih["SIH_Q_MAX"]}}]
    if names == {"SIH_T_TAU"}:
        return [{"name": "motor_time_constant", "params": {"tau_up": sih["SIH_T_TAU"], "tau_down": sih["SIH_T_TAU"]}}]
    if names <= {"SIH_IXX", "SIH_IYY", "SIH_IZZ"}:
        return [{"name": "inertia", "params": {k[4:].lower(): v for k, v in sorted(sih.items())}}]
    if names == {"SIH_KDV"}:
        c = sih["SIH_KDV"]
        return [{"name": "body_drag", "params": {"c_dx": c, "c_dy": c, "c_dz": c, "form": "linear"}}]
    if names == {"SIH_KDW"}:
        return [{"name": "angular_damping", "params": {"k_nm_s_rad": sih["SIH_KDW"]}}]
    if names == {"SIH_MOT_WEAK", "SIH_MOT_EFF"}:
        return [{"name": "motor_efficiency", "params": {"motor": int(sih["SIH_MOT_WEAK"]),
                                                        "efficiency": sih["SIH_MOT_EFF"]}}]
    if names <= {"SIH_CG_X", "SIH_CG_Y"}:   # FRD x forward, y right -> our dx forward, dy left
        return [{"name": "com_offset", "params": {"dx": sih.get("SIH_CG_X", 0.0), "dy": -sih.get("SIH_CG_Y", 0.0)}}]
    if names <= {"SIH_L_ROLL", "SIH_L_PITCH"}:
        return [{"name": "arm_length", "params": {k[4:].lower() + "_m": v for k, v in sorted(sih.items())}}]
    groups = [g for g in _SIH_GROUPS if names & g]
    if len(groups) > 1 and set().union(*groups) >= names:
        # several groups at once (issue 26's two-parameter flights): each group's effect, in the groups' order
        out = []
        for g in groups:
            eff = truth_effects({k: v for k, v in sih.items() if k in g})
            if g == {"SIH_Q_MAX"}:  # km = Q_MAX / T_MAX with the flight's T_MAX
                eff[0]["params"]["km"] = sih["SIH_Q_MAX"] / t_max
            out += eff
        return out
    raise TwinError(f"SIH changes {sorted(names)}: parameter groups (mass, T_MAX, Q_MAX, T_TAU, "
                    "inertia, KDV, KDW, arm lengths; patched: one motor, centre of mass)")


#: the SIH parameter groups a flight's truth is stated by (one effect each)
_SIH_GROUPS = ({"SIH_MASS"}, {"SIH_T_MAX"}, {"SIH_Q_MAX"}, {"SIH_T_TAU"}, {"SIH_IXX", "SIH_IYY", "SIH_IZZ"},
               {"SIH_KDV"}, {"SIH_KDW"}, {"SIH_L_ROLL", "SIH_L_PITCH"}, {"SIH_MOT_WEAK", "SIH_MOT_EFF"},
               {"SIH_CG_X", "SIH_CG_Y"})


def truth_json(sih: dict[str, float], mission: str, ver_sw: str, logging: dict | None = None) -> dict:
    """``truth.json`` of a flight: ``effects``, ``sih_changes`` ``{PARAM: [default, used]}``, ``mission``, ``notes``,
    and ``logging`` (``{"profile", "topics_interval_ms"}``) when a logging profile other than the default was used."""
    changes = {k: [SIH_DEFAULTS[k], v] for k, v in sih.items()}
    text = ", ".join(f"{k} {a:g} -> {b:g}" for k, (a, b) in changes.items()) or "No SIH parameter changed"
    out = {"effects": truth_effects(sih), "sih_changes": changes, "mission": mission,
           "notes": f"{text} (PX4 {ver_sw[:10]} SIH, flown with launch_scripts/fly_sih.sh)."}
    if logging and logging.get("profile") not in (None, "default"):
        out["logging"] = logging
    return out


# --------------------------------------------------------------------------- ULog scrubbing


def _param_name(msg_type: bytes, payload: bytes) -> str | None:
    if msg_type == b"P":
        key = payload[1:1 + payload[0]]
    elif msg_type == b"Q":
        key = payload[2:2 + payload[1]]
    else:
        return None
    return key.decode("ascii", "replace").split(" ", 1)[-1]


def scrub_ulog(src: str | Path, dst: str | Path, prefix: str = "SIH_") -> int:
    """Copy a ULog without the parameter ('P') and default-parameter ('Q') messages whose name starts with
    ``prefix``; every other message is kept byte for byte, in order.  Returns how many were removed.
    A log with appended data (its offsets would move) is refused."""
    data = Path(src).read_bytes()
    if data[:7] != ULOG_MAGIC:
        raise TwinError(f"{src}: not a ULog file (bad magic)")
    out = bytearray(data[:16])
    pos, removed = 16, 0
    while pos + 3 <= len(data):
        size = struct.unpack_from("<H", data, pos)[0]
        mtype = data[pos + 2:pos + 3]
        end = pos + 3 + size
        if end > len(data):  # a truncated last message (log cut at power-off): keep it as it was
            out += data[pos:]
            break
        if mtype == b"B" and size >= 40:
            offsets = struct.unpack_from("<3Q", data, pos + 3 + 16)
            if data[pos + 3 + 8] & 1 or any(offsets):
                raise TwinError(f"{src}: the log has appended data (offsets {offsets}); scrubbing would move it")
        name = _param_name(mtype, data[pos + 3:end])
        if name is not None and name.startswith(prefix):
            removed += 1
        else:
            out += data[pos:end]
        pos = end
    else:
        out += data[pos:]
    Path(dst).write_bytes(bytes(out))
    return removed


def check_scrubbed(original: str | Path, scrubbed: str | Path, prefix: str = "SIH_") -> dict:
    """pyulog opens the scrubbed file; same topics and sample counts, same non-``prefix`` parameters and
    logged messages as the original; the byte string ``prefix`` occurs nowhere."""
    from pyulog import ULog

    a, b = ULog(str(original)), ULog(str(scrubbed))
    counts = {(d.name, d.multi_id): len(d.data["timestamp"]) for d in a.data_list}
    same = counts == {(d.name, d.multi_id): len(d.data["timestamp"]) for d in b.data_list}
    keep = {k: v for k, v in a.initial_parameters.items() if not k.startswith(prefix)}
    return {"opens": True, "same_topics_and_counts": same, "same_other_params": keep == b.initial_parameters,
            "same_messages": [m.message for m in a.logged_messages] == [m.message for m in b.logged_messages],
            "prefix_absent": prefix.encode() not in Path(scrubbed).read_bytes(), "topics": len(counts)}


# --------------------------------------------------------------------------- what the log shows


def log_facts(path: str | Path) -> dict[str, Any]:
    """What the (unscrubbed) log shows: SIH values, mission end, disarm, failsafes, dropouts, warnings,
    airborne time, altitude, speeds, hover thrust estimate."""
    import numpy as np
    from pyulog import ULog

    u = ULog(str(path))
    t0 = u.start_timestamp

    def topic(name):
        d = [x for x in u.data_list if x.name == name and x.multi_id == 0]
        return d[0].data if d else None

    f: dict[str, Any] = {"ver_sw": u.msg_info_dict.get("ver_sw", ""), "duration_s": (u.last_timestamp - t0) * 1e-6,
                         "sih_params": {k: float(v) for k, v in sorted(u.initial_parameters.items())
                                        if k.startswith("SIH_")},
                         "sih_changed_in_flight": sorted({c[1] for c in u.changed_parameters
                                                          if c[1].startswith("SIH_") and c[0] > t0}),
                         "dropouts": len(u.dropouts), "dropout_ms": int(sum(d.duration for d in u.dropouts))}
    msgs = [(m.log_level_str(), m.message) for m in u.logged_messages]
    f["warnings"] = sorted({m for lvl, m in msgs if lvl in ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING")})
    f["disarmed_by_landing"] = any("Disarmed by landing" in m or "Disarmed by auto preflight" in m for _, m in msgs)
    f["gps_drift_warnings"] = sum("Drift" in m for _, m in msgs)
    mr = topic("mission_result")
    f["mission_finished"] = bool(mr is not None and mr["finished"][-1])
    if mr is not None:
        f["mission_seq"] = f"{int(mr['seq_reached'][-1])} of 0-{int(mr['seq_total'][-1]) - 1}"
    vs = topic("vehicle_status")
    if vs is not None:
        f["failsafe"] = bool(np.any(vs["failsafe"]))
        armed = vs["arming_state"] == 2
        if armed.any():
            f["armed_at_s"] = float((vs["timestamp"][np.argmax(armed)] - t0) * 1e-6)
    ld = topic("vehicle_land_detected")
    if ld is not None:
        air = ld["landed"] == 0
        if air.any():
            i0, i1 = np.argmax(air), len(air) - 1 - np.argmax(air[::-1])
            f["airborne_s"] = float((ld["timestamp"][min(i1 + 1, len(air) - 1)] - ld["timestamp"][i0]) * 1e-6)
    lp = topic("vehicle_local_position")
    if lp is not None:
        f["max_alt_m"] = float(np.nanmax(-lp["z"]))
        f["max_ground_speed_m_s"] = float(np.nanmax(np.hypot(lp["vx"], lp["vy"])))
    av = topic("vehicle_angular_velocity")
    if av is not None:
        f["max_yaw_rate_deg_s"] = float(np.degrees(np.nanmax(np.abs(av["xyz[2]"]))))
    ht = topic("hover_thrust_estimate")
    if ht is not None and ht["valid"].any():
        f["hover_thrust_estimate"] = float(np.median(ht["hover_thrust"][ht["valid"] == 1]))
    return f


# --------------------------------------------------------------------------- flying


def px4_binary(px4_dir: str | Path) -> Path:
    b = Path(px4_dir) / "build" / "px4_sitl_default" / "bin" / "px4"
    if not b.is_file():
        raise TwinError(f"{b}: not found (build PX4 first: make px4_sitl_default in {px4_dir})")
    return b


def _wait_for(pred, timeout_s: float, what: str, proc: subprocess.Popen | None = None, poll_s: float = 0.5):
    deadline = time.monotonic() + timeout_s
    while True:
        r = pred()
        if r:
            return r
        if proc is not None and proc.poll() is not None:
            raise TwinError(f"PX4 exited (status {proc.returncode}) while waiting for {what}")
        if time.monotonic() > deadline:
            raise TwinError(f"{what}: not within {timeout_s:g} s")
        time.sleep(poll_s)


def _retry(fn, timeout_s: float, what: str, proc: subprocess.Popen, pause_s: float = 2.0):
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return fn()
        except TwinError as exc:
            if proc.poll() is not None:
                raise TwinError(f"PX4 exited (status {proc.returncode}) during {what}: {exc}") from None
            if time.monotonic() > deadline:
                raise TwinError(f"{what}: still failing after {timeout_s:g} s: {exc}") from None
            time.sleep(pause_s)


def _check_instance_free(instance: int) -> None:
    """Refuse to start when a PX4 of this instance already runs (its offboard link's UDP port 14580+N is
    taken): MAVSDK would fly whichever PX4 answers first."""
    import socket

    port = 14580 + instance
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("0.0.0.0", port))
    except OSError:
        raise TwinError(f"UDP port {port} is taken: another PX4 instance {instance} is running "
                        "(stop it, or use --instance)") from None
    finally:
        s.close()


def _stop(proc: subprocess.Popen, grace_s: float = 15.0) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)  # PX4 shuts down cleanly on SIGINT/SIGTERM
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


def fly_sih(px4_dir: str | Path, plan_file: str | Path, sih: dict[str, float], out_dir: str | Path,
            flight_id: str, *, mission: str = "", manifest: dict | None = None, speed_factor: float | None = None,
            instance: int = 0, timeout_s: float = 1800.0, logging: str | None = None, progress=print) -> dict:
    """Boot PX4 SIH with ``sih`` set, fly ``plan_file``, wait for the disarm, stop PX4, and write
    ``out_dir/flight_id/{flight.ulg (SIH_* scrubbed), truth.json, MANIFEST.md, px4.log}``.  ``logging``: a logging
    profile of the manifest (``px4.logging.profiles``; None = the default topic list).  Returns the facts."""
    from twin_nodes.mavlink.mission import load_plan, start_mission, upload_plan, wait_flight_done

    manifest = manifest or load_manifest()
    topics_text = logger_topics_text(manifest, logging)
    px4 = px4_binary(px4_dir)
    _check_instance_free(instance)
    plan = load_plan(plan_file)
    dest = Path(out_dir) / flight_id
    dest.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f"sih_{flight_id}_"))
    shutil.copytree(px4.parent.parent / "etc", work / "etc", symlinks=False)
    (work / "etc" / "logging").mkdir(exist_ok=True)
    (work / "etc" / "logging" / "logger_topics.txt").write_text(topics_text)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PX4_")}
    env.update({k: str(v) for k, v in manifest["px4"]["environment"].items()})
    if speed_factor is not None:
        env["PX4_SIM_SPEED_FACTOR"] = f"{speed_factor:g}"
    env["HEADLESS"] = "1"
    for k, v in sih.items():
        env[f"PX4_PARAM_{k}"] = f"{v:g}"
    url = f"udpin://0.0.0.0:{14540 + instance}"
    console = dest / "px4.log"
    t_wall = time.monotonic()
    with open(console, "wb") as con:
        proc = subprocess.Popen([str(px4), "-i", str(instance), "-d", "-w", str(work)], cwd=work, env=env,
                                stdout=con, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
        try:
            change = ", ".join(f"{k}={v:g}" for k, v in sih.items()) or "no SIH change"
            progress(f"[{flight_id}] PX4 SIH up (pid {proc.pid}), {change}; uploading {plan.name}")
            up = _retry(lambda: upload_plan(plan, url, connect_timeout_s=20.0, home_timeout_s=30.0), 180.0,
                        "mission upload", proc)
            _retry(lambda: start_mission(url, connect_timeout_s=20.0), 180.0, "arm and start", proc)
            progress(f"[{flight_id}] armed and started ({up['items']} items); waiting for the landing")
            done = wait_flight_done(url, connect_timeout_s=20.0, arm_timeout_s=60.0, timeout_s=timeout_s)
            _wait_for(lambda: b"closed logfile" in console.read_bytes(), 60.0, "the logger closing the log", proc)
        finally:
            _stop(proc)
    wall_s = time.monotonic() - t_wall
    logs = sorted((work / "log").rglob("*.ulg"), key=lambda p: p.stat().st_mtime)
    if not logs:
        raise TwinError(f"{work / 'log'}: PX4 wrote no .ulg (console: {console})")
    raw = logs[-1]
    facts = log_facts(raw)
    for k, v in sih.items():
        got = facts["sih_params"].get(k)
        if got is None and k in SIH_PATCHED:
            raise TwinError(f"{raw}: {k}: not a parameter of this PX4 build: expected one built with "
                            "missions/sih_effects/px4_sih_weak_motor_com.patch (docs/px4_sitl.md)")
        if got is None or not math.isclose(got, v, rel_tol=1e-5):
            raise TwinError(f"{raw}: {k} is {got} in the log, expected {v:g} (PX4_PARAM_{k} not applied)")
    others = {k: v for k, v in facts["sih_params"].items() if k in SIH_DEFAULTS and k not in sih
              and not math.isclose(v, SIH_DEFAULTS[k], rel_tol=1e-5)}
    if others:
        raise TwinError(f"{raw}: SIH parameters not at their defaults: {others}")
    removed = scrub_ulog(raw, dest / "flight.ulg")
    check = check_scrubbed(raw, dest / "flight.ulg")
    if not all(check[k] for k in ("same_topics_and_counts", "same_other_params", "same_messages", "prefix_absent")):
        raise TwinError(f"{dest / 'flight.ulg'}: scrub check failed: {check}")
    facts.update({"removed_sih_messages": removed, "scrub_check": check, "wall_s": wall_s,
                  "flight_wall_s": done["flight_s"], "raw_size_bytes": raw.stat().st_size,
                  "size_bytes": (dest / "flight.ulg").stat().st_size})
    prof = logging or "default"
    over = (manifest["px4"]["logging"].get("profiles") or {}).get(prof, {}).get("topics_interval_ms", {})
    facts["logging"] = {"profile": prof, "topics_interval_ms": dict(over)}
    truth = truth_json(sih, mission or plan.name, facts["ver_sw"], facts["logging"])
    (dest / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    (dest / "MANIFEST.md").write_text(manifest_md(flight_id, truth, facts, plan_file, env, manifest))
    shutil.rmtree(work, ignore_errors=True)
    progress(f"[{flight_id}] done: {facts['duration_s']:.0f} s simulated in {wall_s:.0f} s wall, "
             f"mission finished {facts['mission_finished']}, {facts['size_bytes'] / 1e6:.2f} MB -> {dest}")
    return {"flight": flight_id, "dir": str(dest), "truth": truth, "facts": facts}


def manifest_md(flight_id: str, truth: dict, f: dict, plan_file, env: dict, manifest: dict) -> str:
    """The flight's own MANIFEST.md: how it was flown and what the log shows."""
    px4_env = " ".join(f"{k}={v}" for k, v in sorted(env.items()) if k.startswith("PX4_") or k == "HEADLESS")
    try:
        plan_rel = Path(plan_file).resolve().relative_to(REPO)
    except ValueError:
        plan_rel = Path(plan_file)
    rows = [("PX4", (f"commit `{f['ver_sw']}` (manifest: `{manifest['px4'].get('commit', '?')}`), "
                     "`px4_sitl_default` with gyro_fft and uxrce_dds_client off")),
            ("launch", f"`px4 -i 0 -d -w WORK` (WORK: empty, with etc/ and etc/logging/logger_topics.txt); {px4_env}"),
            ("logging", (f"profile `{f['logging']['profile']}` of the manifest's px4.logging"
                         + (f" (intervals ms changed from the default list: {f['logging']['topics_interval_ms']})"
                            if f["logging"]["topics_interval_ms"] else " (its default topic list)"))),
            ("mission", f"{truth['mission']} (`{plan_rel}`), RTL after, MAVSDK over UDP 14540"),
            ("SIH change", ", ".join(f"{k} {a:g} -> {b:g}" for k, (a, b) in truth["sih_changes"].items()) or "none"),
            ("truth", json.dumps(truth["effects"])),
            ("log", (f"{f['duration_s']:.1f} s simulated ({f['wall_s']:.0f} s wall), {f['size_bytes']} bytes, "
                     f"{f['scrub_check']['topics']} topics")),
            ("SIH values in the log before scrubbing", ", ".join(f"{k} {v:g}" for k, v in f["sih_params"].items()
                                                                  if k in SIH_DEFAULTS)),
            ("scrubbing", f"{f['removed_sih_messages']} 'P'/'Q' SIH_* messages removed; check {f['scrub_check']}"),
            ("mission finished", f"{f['mission_finished']} ({f.get('mission_seq', '?')})"),
            ("disarmed by landing", str(f["disarmed_by_landing"])),
            ("failsafe", str(f.get("failsafe", "?"))),
            ("dropouts", f"{f['dropouts']} ({f['dropout_ms']} ms)"),
            ("GPS drift warnings", str(f["gps_drift_warnings"])),
            ("warnings", "; ".join(f["warnings"]) or "none"),
            ("armed at", f"{f.get('armed_at_s', float('nan')):.1f} s"),
            ("airborne (land detector)", f"{f.get('airborne_s', float('nan')):.1f} s"),
            ("max alt / ground speed / yaw rate", (f"{f.get('max_alt_m', float('nan')):.1f} m / "
                                                   f"{f.get('max_ground_speed_m_s', float('nan')):.1f} m/s / "
                                                   f"{f.get('max_yaw_rate_deg_s', float('nan')):.0f} deg/s")),
            ("hover thrust estimate (median)", f"{f.get('hover_thrust_estimate', float('nan')):.3f}")]
    body = "\n".join(f"| {a} | {b} |" for a, b in rows)
    return (f"# {flight_id}: PX4 SIH flight, {rows[3][1]}\n\nSimulation (PX4's SIH), not hardware. Our own PX4 "
            "output, flown with `launch_scripts/fly_sih.sh` as `missions/sih_effects/manifest.yaml` describes; every "
            "SIH_* parameter is removed from `flight.ulg`, the truth is in `truth.json`.\n\n| item | value |\n|---|---|\n"
            f"{body}\n")


def flights_from_manifest(manifest: dict, ids: list[str]) -> list[dict]:
    """``[{id, mission, plan, sih}]`` for manifest flights ``ids`` (those with a mission of ours, not a shared log)."""
    out = []
    for fid in ids:
        fl = manifest["flights"].get(fid)
        if not isinstance(fl, dict) or "mission" not in fl:
            raise ParamsError(manifest["_path"], f"flights.{fid}", "no such flight (expected mission: and sih:)")
        if fl.get("log"):
            raise ParamsError(manifest["_path"], f"flights.{fid}.log", "a shared log, not a flight fly_sih flies")
        prof = fl.get("logging")
        if prof is not None:
            logging_topics(manifest, prof)  # a known profile, or a one-line error naming it
        out.append({"id": fid, "mission": fl["mission"], "plan": mission_plan_path(manifest, fl["mission"]),
                    "sih": parse_sih(fl.get("sih") or {}, f"{manifest['_path']}: flights.{fid}.sih"),
                    "logging": prof})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="fly_sih", description=__doc__.split("\n\n")[0])
    ap.add_argument("--px4", default=os.environ.get("PX4_DIR"), help="PX4-Autopilot tree built with "
                    "make px4_sitl_default (default $PX4_DIR)")
    ap.add_argument("--out", required=True, help="output folder: <out>/<id>/{flight.ulg,truth.json,MANIFEST.md}")
    ap.add_argument("--manifest", default=str(MANIFEST))
    ap.add_argument("--flight", nargs="+", default=[], help="manifest flight ids to fly (e.g. e09 e10)")
    ap.add_argument("--id", help="an ad-hoc flight: its id (folder name)")
    ap.add_argument("--mission", help="ad-hoc: a manifest mission id (M3) or a plan file")
    ap.add_argument("--sih", nargs="*", default=[], help="ad-hoc: SIH changes NAME=VALUE (none: a no-effect flight)")
    ap.add_argument("--speed-factor", type=float, help="PX4_SIM_SPEED_FACTOR (default: the manifest's)")
    ap.add_argument("--instance", type=int, default=0)
    ap.add_argument("--logging", help="logging profile of the manifest's px4.logging.profiles (e.g. highrate; "
                    "default: a manifest flight's own logging:, else the default topic list)")
    ap.add_argument("--skip-existing", action="store_true", help="skip a flight whose folder has flight.ulg")
    a = ap.parse_args(argv)
    try:
        if not a.px4:
            raise TwinError("--px4: missing (or set PX4_DIR): a PX4-Autopilot tree built with make px4_sitl_default")
        man = load_manifest(a.manifest)
        jobs = flights_from_manifest(man, a.flight)
        if a.id or a.mission:
            if not (a.id and a.mission):
                raise TwinError("--id and --mission go together (an ad-hoc flight)")
            jobs.append({"id": a.id, "mission": a.mission, "plan": mission_plan_path(man, a.mission),
                         "sih": parse_sih(a.sih), "logging": None})
        if a.logging is not None:
            logging_topics(man, a.logging)
            for j in jobs:
                if j["logging"] not in (None, a.logging):
                    raise TwinError(f"--logging {a.logging}: flight {j['id']} is logged with {j['logging']} in "
                                    f"the manifest (flights.{j['id']}.logging)")
                j["logging"] = a.logging
        if not jobs:
            raise TwinError("nothing to fly: give --flight IDS or --id ID --mission M [--sih NAME=VALUE]")
        results = []
        for j in jobs:
            if a.skip_existing and (Path(a.out) / j["id"] / "flight.ulg").is_file():
                print(f"[{j['id']}] exists, skipped")
                continue
            r = fly_sih(a.px4, j["plan"], j["sih"], a.out, j["id"], mission=j["mission"] if j["mission"] in
                        man["missions"] else "", manifest=man, speed_factor=a.speed_factor, instance=a.instance,
                        logging=j["logging"])
            results.append(r)
    except TwinError as exc:
        print(f"fly_sih: {exc}", file=sys.stderr)
        return 1
    for r in results:
        f = r["facts"]
        print(f"{r['flight']}: {r['truth']['effects'][0]['name']} {r['truth']['sih_changes']} "
              f"finished={f['mission_finished']} dropouts={f['dropouts']} {f['size_bytes'] / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
