"""The nominal twin's slow per-motor error on a flight, by mode, regressed on what the log carries (issue 24).

    python tools/slow_error.py FLIGHT.ulg ... [--json OUT.json]

For each flight: the nominal twin (params resolved as ``survey`` does) flies the whole flight closed loop; its
motors less the vehicle's, on the survey's aligned grid, are split at 0.5 Hz (``twin_nodes.twin.metrics.highpass``:
"slow" is the error less its part above 0.5 Hz). On a quad the slow error is taken apart into its four modes
(:data:`MODES`, PX4 motor order). Each mode is regressed, one candidate at a time, on a signal the log carries
(:data:`CANDIDATES`), low-passed the same way: a line fitted on the part before the held-out window (the last 35 %
of the airborne span; the first second after take-off left out) is applied to the held-out part
(:func:`transfer`). A physical effect the twin lacks, or an input it is not given, shows as a line that carries
over: the held-out RMS falls, with slopes of one sign in both parts. The same line fitted on the held-out part
itself is the in-sample bound. A candidate explains a CLASS of flights only where it carries over on several
vehicles with slopes of one sign (the eighteenth session's note in ``docs/corpus.md``).

Only tuning-half flights and ``../shared/flightlogs`` are to be run through this (``docs/corpus_flights.csv``).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

CUTOFF_HZ = 0.5
HELDOUT_FRACTION = 0.35
#: a quad's modes in PX4's motor order (m1 front right ccw, m2 rear left ccw, m3 front left cw, m4 rear right cw):
#: each is the weighted mean of the four motors, so a mode of 1 % moves each motor by 1 %
MODES = {"common": (1.0, 1.0, 1.0, 1.0), "roll": (-1.0, 1.0, 1.0, -1.0), "pitch": (1.0, -1.0, 1.0, -1.0),
         "yaw": (1.0, 1.0, -1.0, -1.0)}
#: the signals each mode is regressed on: pack voltage relative to its median before the held-out window and
#: current (battery), horizontal speed, body-x/y velocity and climb rate (air speed, inflow), height above the
#: take-off spot (ground), yaw rate (yaw damping, a yaw setpoint), the vehicle's own throttle, time (a drift) and
#: the heading's cosine and sine (a wind from one direction)
CANDIDATES = ("vbat", "ibat", "speed_h", "vbx", "vby", "vz", "height", "yaw_rate", "thr_real", "t", "cos_heading",
              "sin_heading")


def lowpass(t: np.ndarray, x: np.ndarray, cutoff_hz: float = CUTOFF_HZ) -> np.ndarray:
    """``x`` less its part above ``cutoff_hz`` (the survey's own high-pass); gaps of ``x`` filled linearly first
    and left NaN after. All NaN where fewer than 32 samples are finite."""
    from twin_nodes.twin.metrics import highpass

    t = np.asarray(t, float)
    x = np.asarray(x, float).ravel()
    ok = np.isfinite(x)
    if ok.sum() < 32:
        return np.full(x.shape, np.nan)
    y = np.interp(t, t[ok], x[ok])
    out = y - highpass(t, y, cutoff_hz)
    out[~ok] = np.nan
    return out


def modes(err: np.ndarray) -> dict[str, np.ndarray]:
    """A quad's (T, 4) per-motor series as its four modes (:data:`MODES`)."""
    err = np.asarray(err, float)
    if err.ndim != 2 or err.shape[1] != 4:
        raise ValueError(f"modes: expected a (T, 4) per-motor series of a quad, got shape {err.shape}")
    return {k: err @ np.asarray(w) / 4.0 for k, w in MODES.items()}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x))) if x.size else math.nan


def transfer(e: np.ndarray, s: np.ndarray, fit: np.ndarray, held: np.ndarray, min_samples: int = 100) -> dict:
    """``e = c0 + c1 s`` fitted on ``fit`` and applied to ``held`` (both boolean masks).

    Returns the slopes fitted on each part (``slope_fit``, ``slope_held``), the correlations (``r_fit``,
    ``r_held``), the held-out RMS of ``e`` as it is (``rms_held``), less the line from the fit part
    (``rms_carried``) and less its own line (``rms_in_sample``); every value NaN where either part has fewer
    than ``min_samples`` finite samples or ``s`` does not vary there."""
    e = np.asarray(e, float)
    s = np.asarray(s, float)
    ok = np.isfinite(e) & np.isfinite(s)
    f, h = np.asarray(fit, bool) & ok, np.asarray(held, bool) & ok
    keys = ("slope_fit", "slope_held", "r_fit", "r_held", "rms_held", "rms_carried", "rms_in_sample")
    if f.sum() < min_samples or h.sum() < min_samples or np.ptp(s[f]) == 0 or np.ptp(s[h]) == 0:
        return dict.fromkeys(keys, math.nan)
    c_f = np.polyfit(s[f], e[f], 1)
    c_h = np.polyfit(s[h], e[h], 1)
    return {"slope_fit": float(c_f[0]), "slope_held": float(c_h[0]),
            "r_fit": float(np.corrcoef(s[f], e[f])[0, 1]), "r_held": float(np.corrcoef(s[h], e[h])[0, 1]),
            "rms_held": _rms(e[h]), "rms_carried": _rms(e[h] - np.polyval(c_f, s[h])),
            "rms_in_sample": _rms(e[h] - np.polyval(c_h, s[h]))}


def carries_over(r: dict, gain: float = 0.85) -> bool:
    """A line that carries over: slopes of one sign in both parts, and the held-out RMS cut below ``gain`` of
    what it was."""
    return bool(np.isfinite(r["rms_carried"]) and r["slope_fit"] * r["slope_held"] > 0
                and r["rms_carried"] < gain * r["rms_held"])


def _heading(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, float).T
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def signals(log, t: np.ndarray, fit: np.ndarray, airborne_start_s: float) -> dict[str, np.ndarray]:
    """The :data:`CANDIDATES` the log carries, on the grid ``t`` (a missing one is absent)."""
    out: dict[str, np.ndarray] = {"t": np.asarray(t, float)}

    def col(name: str, i: int = 0):
        s = log.get(name)
        if s is None or len(s) == 0:
            return None
        v = np.asarray(s.at(t, "linear"), float)
        return v[:, i] if v.ndim > 1 else v

    vb = col("battery_v")
    if vb is not None and np.isfinite(vb[fit]).any():
        out["vbat"] = vb / np.nanmedian(vb[fit]) - 1.0
    ib = col("battery_a")
    if ib is not None:
        out["ibat"] = ib
    v = log.get("velocity_enu")
    v = np.asarray(v.at(t, "linear"), float) if v is not None and len(v) else None
    p = np.asarray(log.require("position_enu").at(t, "linear"), float)
    before = (t > airborne_start_s - 3.0) & (t < airborne_start_s)
    z0 = np.nanmedian(p[before, 2]) if np.isfinite(p[before, 2]).any() else np.nanmin(p[:, 2])
    out["height"] = p[:, 2] - z0
    q = log.get("attitude_q")
    if q is not None and len(q):
        hd = _heading(q.at(t, "slerp"))
        out["cos_heading"], out["sin_heading"] = np.cos(hd), np.sin(hd)
        if v is not None:
            c, s = np.cos(hd), np.sin(hd)
            out["vbx"], out["vby"] = c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]
    if v is not None:
        out["speed_h"], out["vz"] = np.hypot(v[:, 0], v[:, 1]), v[:, 2]
    yr = col("body_rates_flu", 2)
    if yr is not None:
        out["yaw_rate"] = yr
    thr = col("throttle")
    if thr is not None:
        out["thr_real"] = thr
    return out


def flight(path: str | Path) -> dict:
    """The table's rows for one flight: per motor the held-out slow error's P75 and mean, per mode (a quad) its
    held-out RMS and each candidate's :func:`transfer` (percent of full output)."""
    from twin_nodes.identify.nominal import params_for_log
    from twin_nodes.logs.flyable import read_flight
    from twin_nodes.twin.compare import align
    from twin_nodes.twin.runner import run_twin_on_log
    from twin_nodes.vehicle.params import load_params

    log = read_flight(path, horizontal=False)
    pf, _ = params_for_log(path, None, log=log)
    al = align(run_twin_on_log(log, load_params(pf), mode="closed"), log)
    t = np.asarray(al.t, float)
    iv = log.airborne_intervals()
    a, b = iv[0][0], iv[-1][1]
    t_split = a + (1.0 - HELDOUT_FRACTION) * (b - a)
    mask = np.asarray(al.mask, bool)
    held, fit = mask & (t >= t_split), mask & (t < t_split) & (t > a + 1.0)
    err = np.asarray(al.motors_twin, float) - np.asarray(al.motors_real, float)
    slow = np.stack([lowpass(t, err[:, i]) for i in range(err.shape[1])], axis=1)
    row: dict = {"flight": Path(path).stem, "params": pf.name, "held_s": [round(t_split, 2), round(b, 2)],
                 "slow_p75_pct": [], "slow_mean_pct": []}
    for i in range(slow.shape[1]):
        x = slow[held, i]
        x = x[np.isfinite(x)]
        row["slow_p75_pct"].append(float(100 * np.percentile(np.abs(x), 75)) if x.size else math.nan)
        row["slow_mean_pct"].append(float(100 * np.mean(x)) if x.size else math.nan)
    if slow.shape[1] != 4:
        return row
    sig = signals(log, t, fit, a)
    row["modes"] = {}
    for name, e in modes(slow).items():
        cands = {c: transfer(100 * e, lowpass(t, sig[c]) if c != "t" else sig[c], fit, held)
                 for c in CANDIDATES if c in sig}
        row["modes"][name] = {"rms_held_pct": _rms(100 * e[held & np.isfinite(e)]), "candidates": cands}
    return row


def markdown(rows: list[dict]) -> str:
    """Per flight and mode: the held-out RMS and the candidates that carry over (:func:`carries_over`)."""
    lines = ["| flight | held-out slow P75 per motor % | held-out mean per motor % | mode | held-out RMS % "
             "| candidates that carry over (RMS after, slope fit/held per unit) |", "|---|---|---|---|---|---|"]
    for r in rows:
        p75 = "/".join(f"{x:.1f}" for x in r["slow_p75_pct"])
        mean = "/".join(f"{x:+.1f}" for x in r["slow_mean_pct"])
        for j, (m, d) in enumerate((r.get("modes") or {"-": {"rms_held_pct": math.nan, "candidates": {}}}).items()):
            good = sorted(((c, x) for c, x in d["candidates"].items() if carries_over(x)),
                          key=lambda cx: cx[1]["rms_carried"])
            txt = "; ".join(f"{c} {x['rms_carried']:.2f} ({x['slope_fit']:+.3g}/{x['slope_held']:+.3g})"
                            for c, x in good) or "none"
            lead = (r["flight"], p75, mean) if j == 0 else ("", "", "")
            lines.append(f"| {' | '.join(lead)} | {m} | {d['rms_held_pct']:.2f} | {txt} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flights", nargs="+", help="PX4 ULogs (tuning half or ../shared/flightlogs only)")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    rows = []
    for p in args.flights:
        try:
            rows.append(flight(p))
        except Exception as exc:  # one flight that cannot be flown is a line, the rest go on
            print(f"{p}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}", file=sys.stderr)
    print(markdown(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
