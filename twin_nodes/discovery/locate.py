"""Where the model and the flight disagree, and how much each channel was excited.

Channels: ``throttle`` (collective), ``roll``, ``pitch``, ``yaw`` (moment patterns of the
per-motor residual, :func:`~twin_nodes.discovery.residuals.modes`), ``motor1..N`` (each motor's
differential from the collective) and ``force_x``/``force_y`` (horizontal force).

*Mismatch* (:func:`locate`): 2-s windows whose low-passed equation-error RMS exceeds 3x the
channel's own noise floor, labelled by flight regime; :func:`locate_output`: output-error windows
whose error in a mode exceeds 3x the nominal model's typical error there (``"residual": "output"``).

*Events* (:func:`events`): short spans (>= ``EVENT_MIN_S``) where the equation error of the collective
or a moment mode leaves ``EVENT_FACTOR`` x its own flight-long robust spread by at least
``EVENT_MIN_LEVEL`` of full output: a transient no steady candidate effect is made for (a vortex-ring
descent, a motor that did not deliver, a gust), reported with what the vehicle was doing, never fitted.

*Excitation* (:func:`excitation`): what the flight gives a channel to be judged on, from the
commands and the measured motion, not from any residual: per block of the block test, the RMS
deviation of the channel's commanded signal from its trim (low-passed like the residual) against
the channel's floor: its noise, or, when larger, its ordinary level (the median block / 1.5).  A
block is *excited* when it is above ``EXCITED_FACTOR`` x floor (so above twice the median block);
for each channel the number of excited blocks (all, and on the held-out parts the block test
uses) and the manoeuvres (regime labels) they come from.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import butter, sosfiltfilt

from twin_nodes.discovery.residuals import LOWPASS_HZ, EquationData, model_rotor_states, modes
from twin_nodes.physics.model import Multirotor
from twin_nodes.vehicle.params import VehicleParams

EXCITED_FACTOR = 3.0
#: an event: the low-passed residual beyond this many robust standard deviations (1.4826 MAD of the
#: valid samples, about its median) for at least EVENT_MIN_S, on the residual the refitted model leaves
EVENT_FACTOR = 6.0
EVENT_MIN_S = 0.2
#: ... and with a mean of at least this fraction of full output per motor: on a clean log (our simulator,
#: exact model) yaw turns leave 6-25 sigma of a tiny spread but at most 0.016; climb35m's events are 0.11-0.51
EVENT_MIN_LEVEL = 0.05
EVENT_CHANNELS = ("throttle", "roll", "pitch", "yaw")
#: descending faster than this [m/s] with the thrust below the commands: the rotors in their own wake
FAST_DESCENT_M_S = 2.0
#: events lower than this above the take-off ground [m] are take-off and touchdown (spool-up, ground
#: contact, the land detector's lag): not reported
EVENT_MIN_HEIGHT_M = 1.0

#: which manoeuvre supplies each channel (named in verdicts and in the confirmation plans)
SUPPLY = {
    "throttle": "vertical steps (climb/descend between two heights, stop at each)",
    "roll": "roll rate doublets (sideways dashes with hard stops, fly-through zigzag corners)",
    "pitch": "pitch rate doublets (short forward/back dashes with hard stops)",
    "yaw": "yaw sweeps (turns in place: short legs in alternating directions)",
    "force_x": "fast forward legs with accelerations and stops",
    "force_y": "fast sideways/crossing legs",
    "motor": "climbs and hover (each motor loaded)",
}


def regimes(data: EquationData) -> np.ndarray:
    """Flight regime label per sample."""
    v = data.v
    hs = np.hypot(v[:, 0], v[:, 1])
    yaw_rate = np.abs(data.w[:, 2])
    lab = np.full(data.n, "hover", dtype=object)
    lab[hs > 2.0] = "forward 2-5 m/s"
    lab[hs > 5.0] = "forward >5 m/s"
    lab[v[:, 2] > 0.5] = "climb"
    lab[v[:, 2] < -0.5] = "descent"
    lab[yaw_rate > 0.5] = "yaw turn"
    lab[data.height < 1.5] = "near ground"
    batt = data.battery_v
    if np.isfinite(batt).mean() > 0.8:
        lo, hi = np.nanmin(batt), np.nanmax(batt)
        if hi - lo > 0.02 * hi:
            low = batt < lo + 0.3 * (hi - lo)
            lab[low] = np.array([f"{x}, battery low" for x in lab[low]], dtype=object)
    return lab


def channel_signals(R: np.ndarray, vp: VehicleParams, names: list[str]) -> dict[str, np.ndarray]:
    """Per-motor/horizontal channels (T, N + 2) -> every located channel (dict of (T,) arrays)."""
    n_rot = len(names) - 2
    m, mnames = modes(R, vp)
    out = {"throttle": R[:, :n_rot].mean(1)}
    for k in (1, 2, 3):
        out[mnames[k]] = m[:, k]
    coll = R[:, :n_rot].mean(1)
    for i in range(n_rot):
        out[names[i]] = R[:, i] - coll
    out["force_x"] = R[:, n_rot]
    out["force_y"] = R[:, n_rot + 1]
    return out


def _rows(data: EquationData, channel: str) -> np.ndarray:
    """The samples a channel is read on: the vertical force's (``valid``) for the throttle, the longer
    ground-contact pad after a lift-off for the attitude channels (``residuals.contact_pads``)."""
    return data.valid if channel == "throttle" else data.valid_attitude


def _floor(raw: np.ndarray, valid: np.ndarray, fs: float) -> float:
    """Noise floor of a channel after the LOWPASS_HZ filter, from its sample-to-sample differences."""
    hf = np.diff(raw[valid])
    sigma = 1.4826 * np.median(np.abs(hf - np.median(hf))) / math.sqrt(2) if hf.size else 0.0
    return max(sigma * math.sqrt(2 * LOWPASS_HZ / fs), 1e-4)


def locate(data: EquationData, R: np.ndarray, raw: np.ndarray, names: list[str], vp: VehicleParams,
           window_s: float = 2.0, factor: float = 3.0, per_channel: int = 8) -> list[dict]:
    """Time windows, channels and regimes where the residual exceeds its noise floor."""
    lp_ch = channel_signals(R, vp, names)
    raw_ch = channel_signals(raw, vp, names)
    fs = 1.0 / data.dt
    lab = regimes(data)
    per = max(int(round(window_s * fs)), 2)
    out = []
    for ch, lp in lp_ch.items():
        rows = _rows(data, ch)
        floor = _floor(raw_ch[ch], rows, fs)
        flagged = []
        for k0 in range(0, data.n - per + 1, per):
            sl = slice(k0, k0 + per)
            ok = rows[sl]
            if ok.sum() < per // 2:
                continue
            rms = float(np.sqrt(np.mean(lp[sl][ok] ** 2)))
            if rms > factor * floor:
                vals, counts = np.unique(lab[sl][ok], return_counts=True)
                flagged.append([data.t[k0], data.t[min(k0 + per, data.n - 1)], str(vals[np.argmax(counts)]),
                                rms / floor, rms])
        merged: list[list] = []
        for f in flagged:
            if merged and abs(f[0] - merged[-1][1]) < 1e-6 and f[2] == merged[-1][2]:
                merged[-1][1] = f[1]
                merged[-1][3] = max(merged[-1][3], f[3])
                merged[-1][4] = max(merged[-1][4], f[4])
            else:
                merged.append(list(f))
        merged.sort(key=lambda f: -f[3])
        for f in merged[:per_channel]:  # per channel, so a loud channel cannot hide the others
            out.append({"channel": ch, "t_start": round(float(f[0]), 2), "t_end": round(float(f[1]), 2),
                        "regime": f[2], "severity": round(float(f[3]), 2),
                        "rms_fraction_of_full_output": round(float(f[4]), 4)})
    out.sort(key=lambda d: -d["severity"])
    return out


def locate_output(data: EquationData, win, R: np.ndarray, vp: VehicleParams, factor: float = 3.0,
                  per_channel: int = 8) -> list[dict]:
    """Output-error windows whose error in a mode (throttle, roll, pitch, yaw; units of the nominal
    model's typical error on that axis) exceeds ``factor``, merged when they overlap, by regime."""
    m, mnames = modes(R, vp)
    lab = regimes(data)
    out = []
    for k, ch in enumerate(mnames[:4]):
        col = np.abs(m[:, k])
        if not np.any(col):
            continue  # an axis the output error leaves out
        merged: list[list] = []
        for i in np.flatnonzero(col > factor):
            t0, t1 = float(win.t[i]), float(win.t_end[i])
            if merged and t0 <= merged[-1][1] + 1e-6:
                merged[-1][1] = max(merged[-1][1], t1)
                merged[-1][2] = max(merged[-1][2], float(col[i]))
            else:
                merged.append([t0, t1, float(col[i])])
        merged.sort(key=lambda f: -f[2])
        for t0, t1, sev in merged[:per_channel]:
            sel = (data.t >= t0) & (data.t <= t1)
            vals, counts = np.unique(lab[sel], return_counts=True)
            out.append({"channel": ch, "residual": "output", "t_start": round(t0, 2), "t_end": round(t1, 2),
                        "regime": str(vals[np.argmax(counts)]) if counts.size else "", "severity": round(sev, 2)})
    return out


def find_events(t: np.ndarray, valid: np.ndarray, channels: dict[str, np.ndarray],
                factor: float = EVENT_FACTOR, min_s: float = EVENT_MIN_S,
                min_level: float = EVENT_MIN_LEVEL) -> list[dict]:
    """Spans where a channel leaves its own spread: per channel, runs of valid samples with
    ``|x - median| > factor * 1.4826 MAD`` lasting at least ``min_s`` whose mean departs from the
    median by at least ``min_level``; runs of several channels that overlap merge into one event.
    Each: ``t_start``, ``t_end`` and, per channel, the signed peak in robust standard deviations
    (``peak_sigma``, about the median) and the mean value over the run (``mean``)."""
    runs = []
    for ch, x in channels.items():
        v = valid & np.isfinite(x)
        if v.sum() < 10:
            continue
        med = float(np.median(x[v]))
        sig = 1.4826 * float(np.median(np.abs(x[v] - med)))
        if sig <= 0:
            continue
        z = (x - med) / sig
        out = v & (np.abs(z) > factor)
        edges = np.diff(np.concatenate([[0], out.astype(np.int8), [0]]))
        for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1):
            if t[b] - t[a] >= min_s - 1e-9 and abs(float(np.mean(x[a:b + 1])) - med) >= min_level:
                k = a + int(np.argmax(np.abs(z[a:b + 1])))
                runs.append([float(t[a]), float(t[b]), {ch: {"peak_sigma": round(float(z[k]), 1),
                                                             "mean": round(float(np.mean(x[a:b + 1])), 4)}}])
    runs.sort(key=lambda r: r[0])
    merged: list[list] = []
    for r in runs:
        if merged and r[0] <= merged[-1][1] + 1e-9:
            merged[-1][1] = max(merged[-1][1], r[1])
            for ch, v in r[2].items():  # a channel's second run in one event: keep its larger peak
                old = merged[-1][2].get(ch)
                if old is None or abs(v["peak_sigma"]) > abs(old["peak_sigma"]):
                    merged[-1][2][ch] = v
        else:
            merged.append(r)
    return [{"t_start": round(a, 2), "t_end": round(b, 2), "channels": c} for a, b, c in merged]


def events(data: EquationData, R: np.ndarray, vp: VehicleParams, names: list[str],
           factor: float = EVENT_FACTOR, min_s: float = EVENT_MIN_S) -> list[dict]:
    """:func:`find_events` on the collective and moment modes of the equation error ``R``, at least
    ``EVENT_MIN_HEIGHT_M`` above the take-off ground, each with what the vehicle did then (regime,
    vertical and horizontal speed, height, motors at full or zero output) and the physics it points to."""
    ch = channel_signals(R, vp, names)
    airborne = data.valid & (data.height >= EVENT_MIN_HEIGHT_M)
    found = find_events(data.t, airborne, {k: ch[k] for k in EVENT_CHANNELS if k in ch}, factor, min_s)
    if not found:
        return []
    lab = regimes(data)
    u = data.u_fine[::data.up][: data.n]
    for e in found:
        sel = (data.t >= e["t_start"]) & (data.t <= e["t_end"])
        vals, counts = np.unique(lab[sel], return_counts=True)
        vz = data.v[sel, 2]
        us = u[sel]
        full = [i + 1 for i in range(us.shape[1]) if np.nanmax(us[:, i]) >= 0.99]
        idle = [i + 1 for i in range(us.shape[1]) if np.nanmin(us[:, i]) <= 0.01]
        thr = e["channels"].get("throttle")
        e.update({"regime": str(vals[np.argmax(counts)]),
                  "vz_m_s": [round(float(vz.min()), 2), round(float(vz.max()), 2)],
                  "horizontal_speed_m_s": round(float(np.hypot(data.v[sel, 0], data.v[sel, 1]).max()), 2),
                  "height_m": round(float(np.min(data.height[sel])), 2), "motors_at_full": full,
                  "motors_at_zero": idle})
        below = thr is not None and thr["peak_sigma"] < 0  # residual = measured - model: less thrust
        at_full = f" with motor(s) {full} at full output" if full else ""
        if thr is not None and below and vz.min() < -FAST_DESCENT_M_S:
            what = (f"thrust below the commands while descending at up to {-vz.min():.1f} m/s: the rotors in their own "
                    f"wake (vortex ring state); no candidate effect models it")
        elif thr is not None and vz.min() < -FAST_DESCENT_M_S:
            what = (f"thrust above the commands while descending at up to {-vz.min():.1f} m/s{at_full}: the inflow "
                    f"from below raising the rotors' thrust, or a gust")
        elif thr is not None:
            what = (f"thrust {'below' if below else 'above'} the commands{at_full}: "
                    + ("the thrust map near full output, or a motor that did not deliver" if full else "a gust or a transient"))
        else:
            what = f"a moment the commands do not explain{at_full}: a motor that did not deliver, a gust or a payload"
        e["points_to"] = what
    return found


def command_channels(data: EquationData, vp: VehicleParams, names: list[str]) -> dict[str, np.ndarray]:
    """What the flight commands in every channel, in fraction of full motor output: the nominal
    model's rotor thrusts from the logged commands (collective, moment patterns, each motor's
    differential) and the measured horizontal specific force (times mass, per motor)."""
    model = Multirotor(vp)
    S = model_rotor_states(model, data)
    r = model.params.rotors
    tmax = vp.rotors.thrust_at_full_command_n
    T = r.thrust_from_state(np.maximum(S, 0.0)) / tmax
    horiz = vp.mass_kg * data.f[:, :2] / (r.count * tmax)
    return channel_signals(np.column_stack([T, horiz]), vp, names)


def excitation(data: EquationData, vp: VehicleParams, names: list[str], blocks: list[np.ndarray],
               held_blocks: list[np.ndarray] | None = None) -> dict[str, dict]:
    """Per channel: how many blocks carry signal, on the held-out parts and in all, and which
    manoeuvres those are."""
    fs = 1.0 / data.dt
    sos = butter(2, LOWPASS_HZ / (0.5 * fs), output="sos")
    lab = regimes(data)
    held_blocks = blocks if held_blocks is None else held_blocks
    out = {}
    for ch, sig in command_channels(data, vp, names).items():
        rows = _rows(data, ch)
        s = np.where(rows, sig, np.nan)
        trim = float(np.nanmedian(s)) if np.isfinite(s).any() else 0.0
        fill = np.where(np.isfinite(s), s, trim)
        lp = sosfiltfilt(sos, fill - trim)
        # above the channel's noise and above its ordinary level: twice the median block (a flight's
        # cruise keeps every channel a little busy; a manoeuvre is what stands out of that)
        rms = np.array([np.sqrt(np.mean(lp[b] ** 2)) for b in blocks]) if blocks else np.zeros(0)
        typical = float(np.median(rms)) if rms.size else 0.0
        floor = max(_floor(sig, rows, fs), typical / 1.5)

        def excited(bl):
            return [b for b in bl if np.sqrt(np.mean(lp[b] ** 2)) > EXCITED_FACTOR * floor]
        ex_all = excited(blocks)
        ex_held = excited(held_blocks)
        man: dict[str, int] = {}
        for b in ex_held:
            vals, counts = np.unique(lab[b], return_counts=True)
            key = str(vals[np.argmax(counts)])
            man[key] = man.get(key, 0) + 1
        out[ch] = {"blocks_heldout": len(ex_held), "blocks_heldout_total": len(held_blocks),
                   "blocks_flight": len(ex_all), "blocks_flight_total": len(blocks),
                   "manoeuvres": dict(sorted(man.items(), key=lambda kv: -kv[1])),
                   "noise_floor": round(floor, 5)}
    return out


def supply_for(channel: str) -> str:
    """The manoeuvre that excites a channel."""
    if channel.startswith("motor"):
        return SUPPLY["motor"]
    return SUPPLY.get(channel, SUPPLY["pitch"])


__all__ = ["EXCITED_FACTOR", "SUPPLY", "channel_signals", "command_channels", "excitation", "locate",
           "locate_output", "regimes", "supply_for"]
