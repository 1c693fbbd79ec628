"""Twin-versus-real error metrics (pure numpy; no ROS, no I/O).

Definitions (used everywhere: offline ``rotortwin compare``, the live metrics
node and ``rotortwin regress``):

- An error series ``e`` is reduced over its **finite** samples (NaN = "not
  comparable here", e.g. a stopped motor or a sample outside the airborne mask).
- ``rmse``   = ``sqrt(mean(e**2))``
- ``p75``    = 75th percentile of ``|e|``, numpy's default *linear*
  interpolation (``np.percentile(|e|, 75)``: position ``0.75 * (n - 1)`` in the
  sorted ``|e|``, linear between its neighbours)
- ``median`` = median of ``|e|`` (the 50th percentile, same interpolation)
- ``max``    = max of ``|e|``

Error channels (twin minus real, on one common time grid):

- ``xy``: horizontal distance ``||p_twin_xy - p_real_xy||`` [m] (ENU x, y)
- ``z``: altitude difference ``z_twin - z_real`` [m] (ENU up)
- ``throttle``: collective throttle difference [-, 0..1] (PX4 thrust-setpoint
  convention: ``|vehicle_thrust_setpoint.z|``)
- ``motor<i>``: per-motor command difference [-, 0..1], PX4 motor order
  (``motor1`` = PX4 Motor1 = ``actuator_motors.control[0]``)

``xy`` and ``z`` count only where PX4 controlled that axis (``Aligned.xy_mask``/``z_mask``;
``controlled_s``/``controlled_when`` say how long and when); ``throttle_real_hf_rms`` is the real
throttle's own RMS above 0.5 Hz on the scored samples (what a still-air twin cannot follow);
``motor_real_hf_p75_mean`` the real motors' own P75 above 0.5 Hz, the per-motor metric's floor in the same sense;
``divergence`` is where the twin left the real flight (:mod:`twin_nodes.twin.divergence`) or None.

Throttle and motor values are fractions (0.03 = 3 %); :func:`table2` prints
them in percent like the Búho Negro paper's Table 2.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

__all__ = ["STATS", "CHANNELS", "Aligned", "error_stats", "percentile_sorted", "RollingStats",
           "channel_errors", "flight_metrics", "table2", "to_jsonable", "compare_metrics"]

#: the four statistics, in display order
STATS = ("rmse", "p75", "median", "max")
#: scalar error channels (motors are added per motor: motor1, motor2, ...)
CHANNELS = ("xy", "z", "throttle")
#: physical unit suffix of each channel's metric keys
UNITS = {"xy": "_m", "z": "_m", "throttle": "", "motor": ""}


def error_stats(e: Any) -> dict[str, float]:
    """``{rmse, p75, median, max, n}`` of an error series (finite samples only).

    ``e`` is any array; it is flattened.  With no finite sample every statistic
    is NaN and ``n`` is 0."""
    a = np.asarray(e, dtype=float).ravel()
    a = a[np.isfinite(a)]
    if a.size == 0:
        return {"rmse": math.nan, "p75": math.nan, "median": math.nan, "max": math.nan, "n": 0}
    ab = np.abs(a)
    return {
        "rmse": float(np.sqrt(np.mean(a * a))),
        "p75": float(np.percentile(ab, 75.0)),
        "median": float(np.median(ab)),
        "max": float(ab.max()),
        "n": int(a.size),
    }


def percentile_sorted(s: list[float] | np.ndarray, q: float) -> float:
    """Percentile ``q`` (0..100) of an ascending sequence, numpy's 'linear' method."""
    n = len(s)
    if n == 0:
        return math.nan
    pos = (q / 100.0) * (n - 1)
    lo = int(math.floor(pos))
    hi = min(lo + 1, n - 1)
    frac = pos - lo
    return float(s[lo] + (s[hi] - s[lo]) * frac)


class RollingStats:
    """RMSE / P75 / median / max of ``|e|`` over a sliding time window, incrementally.

    The window at the latest time ``t`` holds the samples with
    ``t - window_s < t_i <= t``.  Each :meth:`add` costs O(log n) comparisons
    plus one list insertion/removal (a bisect-maintained sorted list of ``|e|``)
    and O(1) for the running sum of squares; nothing rescans the window.
    Non-finite errors are ignored (they still advance the window).
    """

    def __init__(self, window_s: float):
        if not (math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"window_s: expected a finite window > 0 s, got {window_s}")
        self.window_s = float(window_s)
        self._fifo: deque[tuple[float, float]] = deque()  # (t, |e|) in arrival order
        self._sorted: list[float] = []
        self._sumsq = 0.0
        self._t_last = -math.inf
        self._n_since_exact = 0

    def __len__(self) -> int:
        return len(self._sorted)

    def add(self, t: float, e: float) -> None:
        """Add the error ``e`` observed at time ``t`` (times must not go backwards)."""
        t = float(t)
        if t < self._t_last:
            raise ValueError(f"t: expected non-decreasing times, got {t} after {self._t_last}")
        self._t_last = t
        e = float(e)
        if math.isfinite(e):
            a = abs(e)
            self._fifo.append((t, a))
            bisect.insort(self._sorted, a)
            self._sumsq += a * a
        self._expire(t)

    def advance(self, t: float) -> None:
        """Move the window's end to ``t`` without adding a sample."""
        t = float(t)
        if t > self._t_last:
            self._t_last = t
        self._expire(self._t_last)

    def _expire(self, t: float) -> None:
        lim = t - self.window_s
        fifo, srt = self._fifo, self._sorted
        while fifo and fifo[0][0] <= lim:
            _, a = fifo.popleft()
            del srt[bisect.bisect_left(srt, a)]
            self._sumsq -= a * a
            self._n_since_exact += 1
        if not srt:
            self._sumsq = 0.0
        elif self._n_since_exact > 100_000:
            # bound the floating-point drift of the running sum (rarely: O(n) once per 1e5 removals)
            self._sumsq = math.fsum(a * a for a in srt)
            self._n_since_exact = 0

    def stats(self) -> dict[str, float]:
        """``{rmse, p75, median, max, n}`` of the current window (NaN when empty)."""
        n = len(self._sorted)
        if n == 0:
            return {"rmse": math.nan, "p75": math.nan, "median": math.nan, "max": math.nan, "n": 0}
        s = self._sorted
        return {
            "rmse": math.sqrt(max(self._sumsq, 0.0) / n),
            "p75": percentile_sorted(s, 75.0),
            "median": percentile_sorted(s, 50.0),
            "max": s[-1],
            "n": n,
        }


@dataclass
class Aligned:
    """Twin and real signals on one uniform time grid (built by :func:`twin_nodes.twin.compare.align`
    or by the metrics node from live topics).

    Shapes: ``t`` (n,) s; ``xy_*`` (n, 2) m ENU; ``z_*`` (n,) m ENU up;
    ``throttle_*`` (n,) 0..1; ``motors_*`` (n, N) 0..1 PX4 order, NaN = stopped;
    ``mask`` (n,) bool: the samples that count (airborne, both sides valid)."""

    t: np.ndarray
    xy_twin: np.ndarray
    xy_real: np.ndarray
    z_twin: np.ndarray
    z_real: np.ndarray
    throttle_twin: np.ndarray
    throttle_real: np.ndarray
    motors_twin: np.ndarray
    motors_real: np.ndarray
    mask: np.ndarray
    mode: str = "closed"
    notes: list[str] = field(default_factory=list)
    #: where PX4 controlled the horizontal position / the height (``None``: everywhere); ``xy`` and
    #: ``z`` are scored only there (:func:`twin_nodes.twin.flight_mode.controlled_axes`)
    xy_mask: np.ndarray | None = None
    z_mask: np.ndarray | None = None
    #: the twin's divergence from the real flight (``{"t_s", "cause", "detail"}``; None: none found)
    divergence: dict | None = None
    #: True where the vehicle's own position estimate failed (left out of xy_mask/z_mask; None: not checked)
    estimate_failed: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = np.asarray(self.t).shape[0]
        for name in ("xy_twin", "xy_real", "z_twin", "z_real", "throttle_twin", "throttle_real",
                     "motors_twin", "motors_real", "mask"):
            v = np.asarray(getattr(self, name))
            if v.shape[0] != n:
                raise ValueError(f"Aligned.{name}: expected {n} samples to match t, got shape {v.shape}")
        if np.asarray(self.motors_twin).shape != np.asarray(self.motors_real).shape:
            raise ValueError(f"Aligned.motors_twin {np.asarray(self.motors_twin).shape} and motors_real "
                             f"{np.asarray(self.motors_real).shape}: expected the same shape")

    @property
    def n_motors(self) -> int:
        return int(np.asarray(self.motors_real).reshape(len(self.t), -1).shape[1])


def channel_errors(al: Aligned) -> dict[str, np.ndarray]:
    """Error series per channel (twin minus real; ``xy`` is a distance), NaN outside ``mask``."""
    mask = np.asarray(al.mask, bool)
    out = {
        "xy": np.linalg.norm(np.asarray(al.xy_twin, float) - np.asarray(al.xy_real, float), axis=1),
        "z": np.asarray(al.z_twin, float) - np.asarray(al.z_real, float),
        "throttle": np.asarray(al.throttle_twin, float) - np.asarray(al.throttle_real, float),
    }
    n = len(al.t)
    mt = np.asarray(al.motors_twin, float).reshape(n, -1)
    mr = np.asarray(al.motors_real, float).reshape(n, -1)
    for i in range(mr.shape[1]):
        out[f"motor{i + 1}"] = mt[:, i] - mr[:, i]
    for k, v in out.items():
        v = np.array(v, dtype=float)
        v[~mask] = np.nan
        axis = al.xy_mask if k == "xy" else al.z_mask if k == "z" else None
        if axis is not None:
            v[~np.asarray(axis, bool)] = np.nan
        out[k] = v
    return out


def _intervals(t: np.ndarray, flag: np.ndarray, dt: float) -> list[list[float]]:
    """[start, end] of each run of True in ``flag`` (times ``t``), rounded to 0.1 s."""
    out: list[list[float]] = []
    idx = np.flatnonzero(flag)
    if idx.size == 0:
        return out
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    return [[round(float(t[a]), 1), round(float(t[b] + dt), 1)] for a, b in zip(starts, ends)]


#: the real throttle's content above this [Hz] is the floor no still-air twin can follow (turbulence,
#: gusts, the pilot's stick): ``throttle_real_hf_rms``
HF_CUTOFF_HZ = 0.5


def highpass(t: np.ndarray, x: np.ndarray, cutoff_hz: float = HF_CUTOFF_HZ) -> np.ndarray:
    """``x`` high-passed at ``cutoff_hz`` (2nd-order Butterworth, forward-backward, over each run of
    finite samples of the uniform grid ``t`` at least one period of the cut-off long); NaN elsewhere."""
    from scipy.signal import butter, sosfiltfilt

    t = np.asarray(t, float)
    x = np.asarray(x, float).ravel()
    hp = np.full(x.shape, np.nan)
    if t.size < 16:
        return hp
    fs = 1.0 / float(np.median(np.diff(t)))
    if not cutoff_hz < 0.45 * fs:
        return hp
    sos = butter(2, cutoff_hz, btype="highpass", fs=fs, output="sos")
    idx = np.flatnonzero(np.isfinite(x))
    if idx.size == 0:
        return hp
    breaks = np.flatnonzero(np.diff(idx) > 1)
    for a, b in zip(np.concatenate([[idx[0]], idx[breaks + 1]]), np.concatenate([idx[breaks], [idx[-1]]])):
        if b - a + 1 >= int(fs / cutoff_hz) and b - a + 1 > 12:  # at least one period of the cut-off
            hp[a:b + 1] = sosfiltfilt(sos, x[a:b + 1])
    return hp


def highpass_rms(t: np.ndarray, x: np.ndarray, mask: np.ndarray, cutoff_hz: float = HF_CUTOFF_HZ) -> float:
    """RMS over ``mask`` of ``x`` high-passed at ``cutoff_hz`` (:func:`highpass`); NaN when nothing is left."""
    hp = highpass(t, x, cutoff_hz)
    v = hp[np.asarray(mask, bool) & np.isfinite(hp)]
    return float(np.sqrt(np.mean(v * v))) if v.size else math.nan


def motors_highpass_p75(t: np.ndarray, motors: np.ndarray, mask: np.ndarray,
                        cutoff_hz: float = HF_CUTOFF_HZ) -> float:
    """Mean over the motors of the P75 of ``|motor|`` high-passed at ``cutoff_hz`` over ``mask``: the real
    motors' own content a still-air twin cannot follow, in the per-motor metric's own terms (a twin
    that is exact below the cut-off and flat above it scores this); NaN when nothing is left."""
    m = np.atleast_2d(np.asarray(motors, float))
    p75 = []
    for i in range(m.shape[1]):
        hp = highpass(t, m[:, i], cutoff_hz)
        v = hp[np.asarray(mask, bool) & np.isfinite(hp)]
        if v.size:
            p75.append(float(np.percentile(np.abs(v), 75.0)))
    return float(np.mean(p75)) if p75 else math.nan


def flight_metrics(al: Aligned) -> dict[str, Any]:
    """Whole-flight metrics with self-explaining keys (see the module docstring).

    Keys: ``xy_{rmse,p75,median,max}_m``, ``z_..._m``, ``throttle_...`` (fraction),
    ``motor_{rmse,p75,median,max}`` (lists, PX4 motor order), ``motor_p75_mean``,
    ``duration_s`` (span of the counted samples), ``n_samples``, ``n_motors``, ``mode``,
    ``rate_hz`` and ``definitions``."""
    err = channel_errors(al)
    mask = np.asarray(al.mask, bool)
    t = np.asarray(al.t, float)
    out: dict[str, Any] = {}
    for ch in CHANNELS:
        s = error_stats(err[ch])
        for st in STATS:
            out[f"{ch}_{st}{UNITS[ch]}"] = s[st]
    motor = [error_stats(err[f"motor{i + 1}"]) for i in range(al.n_motors)]
    for st in STATS:
        out[f"motor_{st}"] = [m[st] for m in motor]
    p75 = [v for v in out["motor_p75"] if math.isfinite(v)]
    out["motor_p75_mean"] = float(np.mean(p75)) if p75 else math.nan
    out["duration_s"] = float(t[mask][-1] - t[mask][0]) if mask.sum() > 1 else 0.0
    out["n_samples"] = int(mask.sum())
    out["n_motors"] = al.n_motors
    out["mode"] = al.mode
    out["rate_hz"] = float(1.0 / np.median(np.diff(t))) if t.size > 1 else math.nan
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    out["controlled_s"], out["controlled_when"] = {}, {}
    for ax, am in (("xy", al.xy_mask), ("z", al.z_mask)):
        on = mask & (np.ones(mask.shape, bool) if am is None else np.asarray(am, bool))
        on &= np.isfinite(err[ax])
        out["controlled_s"][ax] = round(float(on.sum()) * dt, 2)
        out["controlled_when"][ax] = _intervals(t, on, dt)[:20]
    out["controlled_axes"] = [ax for ax in ("xy", "z") if out["controlled_s"][ax] > 0]
    ef = np.zeros(mask.shape, bool) if al.estimate_failed is None else np.asarray(al.estimate_failed, bool)
    out["estimate_failed_s"] = round(float((mask & ef).sum()) * dt, 2)
    out["throttle_real_hf_rms"] = highpass_rms(t, al.throttle_real, mask, HF_CUTOFF_HZ)
    out["motor_real_hf_p75_mean"] = motors_highpass_p75(t, al.motors_real, mask, HF_CUTOFF_HZ)
    out["divergence"] = dict(al.divergence) if al.divergence else None
    out["definitions"] = ("errors are twin minus real on a common grid over the masked (airborne) samples; "
                          "xy = horizontal distance [m], z = altitude difference [m], throttle and motors "
                          "are fractions 0..1 (PX4 normalised); rmse = sqrt(mean(e^2)); p75/median = 75th/50th "
                          "percentile of |e| (numpy linear interpolation); max = max |e|; xy and z only where "
                          "PX4 controlled that axis (controlled_s, controlled_when: a position or velocity "
                          "setpoint finite in it while mc_pos_control runs); divergence: where the twin left "
                          "the real flight's envelope (t_s, cause) or null")
    if al.notes:
        out["notes"] = list(al.notes)
    return out


def _f(v: Any, scale: float = 1.0, digits: int = 3) -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return "-"
    return "n/a" if not math.isfinite(x) else f"{x * scale:.{digits}f}"


def table2(m: Mapping[str, Any], title: str = "") -> str:
    """The metrics in the layout of the Búho Negro paper's Table 2 (plain text)."""
    motors = " ".join(f"M{i + 1} {_f(v, 100, 1)}" for i, v in enumerate(m.get("motor_p75", [])))
    rows = [
        ("XY trajectory RMSE [m]", _f(m.get("xy_rmse_m"))),
        ("XY trajectory P75 [m]", _f(m.get("xy_p75_m"))),
        ("Altitude RMSE [m]", _f(m.get("z_rmse_m"))),
        ("Altitude P75 [m]", _f(m.get("z_p75_m"))),
        ("Per-motor output P75 [%]", f"{_f(m.get('motor_p75_mean'), 100, 1)} (mean; {motors})"),
        ("Throttle RMSE [%]", _f(m.get("throttle_rmse"), 100, 1)),
        ("Throttle median [%]", _f(m.get("throttle_median"), 100, 1)),
    ]
    w = max(len(r[0]) for r in rows)
    head = title or "Twin vs real (Table 2 layout)"
    sub = (f"mode {m.get('mode', '?')}, {m.get('n_samples', '?')} samples over "
           f"{_f(m.get('duration_s'), 1, 1)} s at {_f(m.get('rate_hz'), 1, 0)} Hz")
    lines = [head, sub, "-" * (w + 30)]
    lines += [f"{name:<{w}}  {val}" for name, val in rows]
    cs = m.get("controlled_s") or {}
    if cs:
        lines.append("Axes PX4 controlled [s]".ljust(w) + "  " + ", ".join(f"{k} {_f(v, 1, 1)}" for k, v in cs.items()))
    dv = m.get("divergence")
    lines.append("Divergence".ljust(w) + "  " + (f"at {_f(dv.get('t_s'), 1, 1)} s: {dv.get('cause')}"
                                               if dv else "none"))
    for note in m.get("notes", []) or []:
        lines.append(f"note: {note}")
    return "\n".join(lines)


def to_jsonable(obj: Any) -> Any:
    """Copy of ``obj`` that ``json.dumps`` writes as strict JSON (NaN/inf -> None, numpy -> Python)."""
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    return obj


def compare_metrics(stored: Mapping[str, Any], fresh: Mapping[str, Any], rel_tol: float = 0.05,
                    abs_tol: float = 1e-3) -> list[str]:
    """Regression check: every numeric metric in ``stored`` must match ``fresh`` within
    ``max(abs_tol, rel_tol * |stored|)``.  Returns one line per violation (empty = pass)."""
    bad: list[str] = []
    for key, old in stored.items():
        if key in ("n_samples", "duration_s", "rate_hz", "n_motors"):
            continue
        new = fresh.get(key)
        olds = old if isinstance(old, list) else [old]
        news = new if isinstance(new, list) else [new]
        if not all(isinstance(v, (int, float)) or v is None for v in olds):
            continue
        if len(olds) != len(news):
            bad.append(f"{key}: stored {old}, now {new} (different length)")
            continue
        for i, (a, b) in enumerate(zip(olds, news)):
            name = f"{key}[{i}]" if isinstance(old, list) else key
            a_nan = a is None or (isinstance(a, float) and not math.isfinite(a))
            b_nan = b is None or (isinstance(b, float) and not math.isfinite(b))
            if a_nan or b_nan:
                if a_nan != b_nan:
                    bad.append(f"{name}: stored {a}, now {b}")
                continue
            tol = max(abs_tol, rel_tol * abs(float(a)))
            if abs(float(b) - float(a)) > tol:
                bad.append(f"{name}: stored {float(a):.6g}, now {float(b):.6g} (tolerance {tol:.3g})")
    return bad
