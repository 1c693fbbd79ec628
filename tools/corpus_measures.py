"""Per-flight measures for judging the corpus survey against issue 24's targets (the measuring half of 24.7).

    python tools/corpus_measures.py FLIGHT.ulg|DIR ... [--survey SURVEY.json] [--md OUT.md]

For each flight, on the held-out window (the survey's ``interval_s`` where the survey has the flight,
else the last 35 % of the airborne span as ``FlightLog.airborne_interval`` gives it):

- ``floor``: the logged throttle's own content above 0.5 Hz -- the RMS of ``throttle`` minus its
  zero-phase 2nd-order Butterworth low-pass at 0.5 Hz, on a uniform grid at the throttle's median
  logging rate.  A still-air twin cannot follow gusts and pilot stick inputs faster than that, so
  issue 24 accepts a throttle RMSE up to ``max(3 %, 1.25 * floor)``.
- ``xy`` / ``z`` controlled: the fraction of the window whose PX4 ``nav_state`` holds that axis
  (XY: POSCTL, AUTO_*, OFFBOARD, ORBIT, DESCEND; Z: those and ALTCTL; MANUAL/STAB/ACRO hold neither).
  An axis counts as controlled when it is held over at least half of the window.
- with ``--survey``: the verdict per flight against the targets (throttle as above, per-motor P75
  <= 5 %, XY <= 1.0 m and Z <= 0.5 m only where controlled).

Reads logs through ``twin_nodes.logs.ulog_io.read_ulog`` (no flyability check), so time bases match
the survey.  An unreadable flight is a row with its one-line error.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.signal import butter, sosfiltfilt

CUTOFF_HZ = 0.5
HELDOUT_FRACTION = 0.35
#: nav_state values (PX4 vehicle_status) in which PX4 holds horizontal position / altitude
XY_HELD = {2, 3, 4, 5, 12, 14, 17, 18, 19, 20, 21, 22}
Z_HELD = XY_HELD | {1}
TARGETS = {"throttle": 0.03, "floor_factor": 1.25, "motor_p75": 0.05, "xy_m": 1.0, "z_m": 0.5}


def high_freq_rms(t: np.ndarray, x: np.ndarray, cutoff_hz: float = CUTOFF_HZ) -> float:
    """RMS of ``x`` above ``cutoff_hz``: ``x`` minus its zero-phase Butterworth low-pass, on a uniform
    grid at the median sample rate.  NaN when there are too few samples for the filter."""
    ok = np.isfinite(t) & np.isfinite(x)
    t, x = t[ok], x[ok]
    if t.size < 16:
        return float("nan")
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        return float("nan")
    fs = 1.0 / dt
    if cutoff_hz >= 0.45 * fs:
        return float("nan")
    grid = np.arange(t[0], t[-1], dt)
    xu = np.interp(grid, t, x)
    sos = butter(2, cutoff_hz, btype="low", fs=fs, output="sos")
    if xu.size <= 3 * (2 * len(sos) + 1):
        return float("nan")
    return float(np.sqrt(np.mean((xu - sosfiltfilt(sos, xu)) ** 2)))


def held_fraction(t_nav: np.ndarray, nav: np.ndarray, t0: float, t1: float, held: set[int]) -> float:
    """Fraction of [t0, t1] during which the (step-held) ``nav`` value is in ``held``."""
    if t_nav.size == 0 or not t1 > t0:
        return float("nan")
    grid = np.linspace(t0, t1, 501)
    idx = np.searchsorted(t_nav, grid, side="right") - 1
    vals = np.where(idx >= 0, nav[np.clip(idx, 0, None)], np.nan)
    return float(np.mean(np.isin(vals, list(held))))


def measure(path: Path, window: tuple[float, float] | None) -> dict:
    from twin_nodes.logs.ulog_io import read_ulog
    log = read_ulog(path)
    if window is None:
        a, b = log.airborne_interval()
        window = (a + (1.0 - HELDOUT_FRACTION) * (b - a), b)
    t0, t1 = window
    row: dict = {"flight": path.stem, "window_s": [round(t0, 2), round(t1, 2)]}
    thr = log.get("throttle")
    if thr is not None:
        sel = (thr.t_s >= t0) & (thr.t_s <= t1)
        row["floor"] = high_freq_rms(thr.t_s[sel], thr.values[sel, 0])
        row["throttle_source"] = thr.source
    nav = log.get("nav_state")
    if nav is not None and len(nav):
        row["xy_held"] = held_fraction(nav.t_s, nav.values[:, 0], t0, t1, XY_HELD)
        row["z_held"] = held_fraction(nav.t_s, nav.values[:, 0], t0, t1, Z_HELD)
    return row


def verdict(row: dict, m: dict) -> tuple[bool, list[str]]:
    """Against the targets; returns (meets, what fails)."""
    fails = []
    floor = row.get("floor", float("nan"))
    allowed = max(TARGETS["throttle"], TARGETS["floor_factor"] * floor) if np.isfinite(floor) else TARGETS["throttle"]
    if not m["throttle_rmse"] <= allowed:
        fails.append(f"throttle {100 * m['throttle_rmse']:.1f} > {100 * allowed:.1f} %")
    if not m["motor_p75_mean"] <= TARGETS["motor_p75"]:
        fails.append(f"P75 {100 * m['motor_p75_mean']:.1f} > 5 %")
    if row.get("xy_held", 0) >= 0.5 and not m["xy_rmse_m"] <= TARGETS["xy_m"]:
        fails.append(f"XY {m['xy_rmse_m']:.2f} > 1.0 m")
    if row.get("z_held", 0) >= 0.5 and not m["z_rmse_m"] <= TARGETS["z_m"]:
        fails.append(f"Z {m['z_rmse_m']:.2f} > 0.5 m")
    return not fails, fails


def _flights(args: list[str]) -> list[Path]:
    out: list[Path] = []
    for a in args:
        p = Path(a)
        out += sorted(p.glob("*.ulg")) if p.is_dir() else [p]
    return out


def _fmt(x: float | None, scale: float = 1.0, nd: int = 1) -> str:
    return "" if x is None or not np.isfinite(x) else f"{scale * x:.{nd}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+")
    ap.add_argument("--survey", type=Path, action="append", default=[], help="survey --json output(s)")
    ap.add_argument("--md", type=Path, help="write the table here")
    a = ap.parse_args(argv)
    surveyed = {}
    for s in a.survey:
        for r in json.loads(s.read_text())["rows"]:
            surveyed[r["flight"]] = r
    lines = ["| flight | window s | throttle >0.5 Hz % | allowed throttle % | XY held | Z held | survey | verdict |",
             "|---|---|---|---|---|---|---|---|"]
    for path in _flights(a.flights):
        s = surveyed.get(path.stem)
        ok = s is not None and s.get("status") == "ok"
        window = tuple(s["before"]["interval_s"]) if ok else None
        try:
            row = measure(path, window)
        except Exception as exc:  # one row per unreadable flight; the rest go on
            lines.append(f"| {path.stem} | | | | | | | not measured: {str(exc).splitlines()[0]} |")
            continue
        floor = row.get("floor", float("nan"))
        allowed = max(TARGETS["throttle"], TARGETS["floor_factor"] * floor) if np.isfinite(floor) else TARGETS["throttle"]
        if ok:
            b = s["before"]
            meets, fails = verdict(row, b)
            surv = f"{100 * b['throttle_rmse']:.1f} / {100 * b['motor_p75_mean']:.1f} / {b['xy_rmse_m']:.2f} / {b['z_rmse_m']:.2f}"
            verd = "meets targets" if meets else "; ".join(fails)
        else:
            surv, verd = ("failed" if s else "not surveyed"), "did not start" if s else ""
        lines.append(f"| {path.stem} | {row['window_s'][0]:.0f}-{row['window_s'][1]:.0f} | {_fmt(floor, 100)} | "
                     f"{100 * allowed:.1f} | {_fmt(row.get('xy_held'), 100, 0)} % | {_fmt(row.get('z_held'), 100, 0)} % | "
                     f"{surv} | {verd} |")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    if a.md:
        a.md.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
