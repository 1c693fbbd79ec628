"""What ``rotortwin identify`` reports: one result type per method, and the parameter-file block.

Every result (built by :mod:`twin_nodes.identify.from_log`) carries

- ``block``: only parameter-file keys (a ``ros__parameters`` fragment), to merge
  with :func:`merge_into_params` and check with :func:`check_merged`;
- ``report``: the full result as a dict (all numbers, standard errors, segments, notes);
- ``notes``: one-line caveats about the data or the method;
- ``summary_lines()``: the console summary (tables and key numbers, no notes);
- ``plot(path)``: a PNG figure (:mod:`twin_nodes.identify.plots`).

Numbers in ``report`` may be numpy types, NaN or inf; :func:`plain` turns them
into what YAML / JSON can hold.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from twin_nodes.identify import plots
from twin_nodes.identify.delay import DelayEstimate
from twin_nodes.identify.hover import HoverSegment, HoverSummary
from twin_nodes.identify.noise import ImuNoise
from twin_nodes.identify.regression import (LinearFit, RotorGeometry, StructuralResult, rotational_columns,
                                            translational_columns)
from twin_nodes.identify.step_response import RPM_TO_RAD_S, DiscreteLag, StepFit
from twin_nodes.vehicle.params import VehicleParams, from_ros_dict

# --------------------------------------------------------------------------- parameter-file block and plain types


def merge_into_params(base_ros: dict, block: dict) -> dict:
    """``base_ros`` (a ``ros__parameters`` mapping) with the identified ``block`` merged in (deep copy)."""
    out = copy.deepcopy(base_ros)
    for k, v in block.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge_into_params(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def check_merged(vp: VehicleParams, block: dict, path: str) -> VehicleParams:
    """``vp`` with ``block`` merged in, validated by the params schema (raises ``ParamsError``; ``path`` names it)."""
    return from_ros_dict(merge_into_params(vp.to_ros_dict(), block), path=path)


def plain(obj: Any, for_json: bool = False) -> Any:
    """Plain Python types for YAML/JSON; NaN -> None; inf stays a float (YAML .inf), a JSON "inf" string."""
    if isinstance(obj, dict):
        return {str(k): plain(v, for_json) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v, for_json) for v in obj]
    if isinstance(obj, np.ndarray):
        return [plain(v, for_json) for v in obj.tolist()]
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        if math.isnan(v):
            return None
        if math.isinf(v) and for_json:
            return "inf" if v > 0 else "-inf"
        return v
    return obj


def _table(rows: list[tuple[str, ...]], header: tuple[str, ...] | None = None) -> list[str]:
    """Left-aligned text columns, with a dashed rule under ``header``."""
    allrows = ([header] if header else []) + rows
    widths = [max(len(str(r[i])) for r in allrows) for i in range(len(allrows[0]))]
    lines = []
    for j, r in enumerate(allrows):
        lines.append("  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip())
        if header and j == 0:
            lines.append("  ".join("-" * w for w in widths))
    return lines


def _g(v: float | None, nd: int = 4) -> str:
    return "nan" if v is None or not np.isfinite(v) else f"{v:.{nd}g}"


# --------------------------------------------------------------------------- motor


@dataclass(frozen=True)
class MotorFit:
    """Symmetric and up/down fits of one command (``t_u`` [s], ``u``) -> rotor speed (``t_y`` [s], ``y`` [rpm])
    record, and the symmetric fit's ZOH difference equation."""

    name: str
    t_u: np.ndarray
    u: np.ndarray
    t_y: np.ndarray
    y: np.ndarray
    symmetric: StepFit
    asymmetric: StepFit
    zoh: DiscreteLag


@dataclass(frozen=True)
class MotorResult:
    """Motor lag fits; ``tau_up_s``/``tau_down_s`` [s] are the medians over ``fits`` (written to ``rotors``)."""

    source: str
    rate_hz: float
    u_label: str
    fits: list[MotorFit]
    tau_up_s: float
    tau_down_s: float
    notes: list[str]

    @property
    def block(self) -> dict:
        return {"rotors": {"tau_up_s": self.tau_up_s, "tau_down_s": self.tau_down_s}}

    def _fit_report(self, f: MotorFit) -> dict:
        def pole(tau_s: float) -> float:
            """ZOH pole ``exp(-T / tau)`` at ``rate_hz``."""
            return math.exp(-1.0 / (self.rate_hz * tau_s)) if tau_s > 0 else 0.0

        return {"symmetric": f.symmetric.as_dict(), "asymmetric": f.asymmetric.as_dict(),
                "gain_rad_s_per_unit": f.symmetric.gain * RPM_TO_RAD_S,
                "zoh": {**f.zoh.as_dict(), "equation": "y[k+1] = a*y[k] + b[0]*u[k-n] + b[1]*u[k-n-1] + c",
                        "closed_form_a": pole(f.symmetric.tau_s), "a_up": pole(f.asymmetric.tau_up_s),
                        "a_down": pole(f.asymmetric.tau_down_s)}}

    @property
    def report(self) -> dict:
        return {"kind": "motor", "source": self.source, "fits": {f.name: self._fit_report(f) for f in self.fits},
                "notes": self.notes, "zoh_rate_hz": self.rate_hz}

    def summary_lines(self) -> list[str]:
        rows = [(f.name, label, _g(s.tau_up_s), _g(s.tau_down_s), _g(s.gain), _g(s.gain_stderr, 2),
                 f"{s.delay_s * 1e3:.1f}", _g(s.r2, 5), _g(s.rmse))
                for f in self.fits for label, s in (("symmetric", f.symmetric), ("up/down", f.asymmetric))]
        lines = _table(rows, ("data", "model", "tau_up_s", "tau_down_s", "K", "se(K)", "delay_ms", "R2", "rmse"))
        for f in self.fits:
            z = self._fit_report(f)["zoh"]
            lines.append(f"{f.name}: ZOH at {self.rate_hz:g} Hz: a = {z['a']:.6f} (exp(-T/tau) = "
                         f"{z['closed_form_a']:.6f}), b = [{z['b'][0]:.6g}, {z['b'][1]:.6g}], c = {z['c']:.6g}, "
                         f"n = {z['delay_samples']}")
        lines.append(f"rotors.tau_up_s = {self.tau_up_s:.5g} s, rotors.tau_down_s = {self.tau_down_s:.5g} s")
        return lines

    def plot(self, path: str) -> None:
        f = self.fits[0]
        plots.plot_step_fit(path, f.t_u, f.u, f.t_y, f.y, {"symmetric": f.symmetric, "up/down": f.asymmetric},
                            u_label=self.u_label, title=f"{Path(self.source).name} ({f.name})")


# --------------------------------------------------------------------------- hover


@dataclass(frozen=True)
class HoverFlight:
    """Steady-hover segments of a flight on a 10 Hz grid ``t`` [s].

    ``throttle`` (n,) collective command; ``velocity_enu`` (n, 3) [m/s];
    ``hover_estimate`` (n, 1) PX4's hover thrust estimate or None;
    ``motor_means`` (N,) duration-weighted per-motor command over the segments or None;
    ``hover_estimate_in_segments`` PX4's estimate averaged over each segment or None;
    ``rpm_logged``: every segment has positive per-rotor RPM.
    """

    source: str
    t: np.ndarray
    throttle: np.ndarray
    velocity_enu: np.ndarray
    hover_estimate: np.ndarray | None
    segments: list[HoverSegment]
    summary: HoverSummary
    motor_means: np.ndarray | None
    hover_estimate_in_segments: list[float] | None
    rpm_logged: bool
    px4_hover_throttle: float | None
    sitl: bool

    def summary_lines(self) -> list[str]:
        rows = [(f"{s.t_start_s:.1f}-{s.t_end_s:.1f}", f"{s.duration_s:.1f}", f"{s.throttle_mean:.4f}",
                 f"{s.throttle_std:.4f}",
                 "-" if s.motors_mean is None else " ".join(f"{x:.3f}" for x in s.motors_mean),
                 "-" if s.rpm_mean is None else " ".join(f"{x:.0f}" for x in s.rpm_mean))
                for s in self.segments]
        m = self.summary
        return _table(rows, ("segment_s", "dur_s", "throttle", "std", "motors_mean", "rpm_mean")) + [
            f"hover throttle {m.throttle_mean:.4f} (between segments {m.between_std:.4f}, within {m.within_std:.4f}) "
            f"over {m.n_segments} segment(s), {m.total_s:.1f} s; PX4 MPC_THR_HOVER {self.px4_hover_throttle}"]


@dataclass(frozen=True)
class HoverResult:
    """The rotor parameter a hover implies: ``kt`` from RPM (``kt``: value [N/(rad/s)^2], per segment,
    spread, mass [kg], gravity [m/s^2]), or from the hover command through the map of the params file
    ``params_source`` (``derived``: hover command, the parameter, thrust model), or none."""

    flight: HoverFlight
    block: dict
    notes: list[str]
    kt: dict | None = None
    derived: dict | None = None
    params_source: str = ""

    @property
    def report(self) -> dict:
        fl = self.flight
        out: dict = {"kind": "hover", "source": fl.source, "summary": fl.summary.as_dict(),
                     "segments": [s.as_dict() for s in fl.segments], "notes": self.notes,
                     "px4_MPC_THR_HOVER": fl.px4_hover_throttle}
        if fl.motor_means is not None:
            out["motor_command_mean"] = fl.motor_means
            out["motor_command_mean_all"] = float(np.mean(fl.motor_means))
        if fl.hover_estimate_in_segments is not None:
            out["px4_hover_thrust_estimate_in_segments"] = fl.hover_estimate_in_segments
        if self.kt is not None:
            out["kt_n_s2_rad2"] = self.kt
        if self.derived is not None:
            out["derived_from_hover_command"] = self.derived
        return out

    def summary_lines(self) -> list[str]:
        if self.kt is not None:
            return [f"kt = m g / sum(w_i^2) = {self.kt['value']:.5g} N/(rad/s)^2 "
                    f"(per segment {', '.join(_g(k) for k in self.kt['per_segment'])})"]
        if self.derived is not None:
            k, val = next(iter(self.block["rotors"].items()))
            return [f"no RPM in the log: hover command {self.derived['hover_command']:.4f} with "
                    f"{self.params_source}'s {self.derived['thrust_model']} map gives rotors.{k} = {val:.5g}"]
        return []

    def plot(self, path: str) -> None:
        fl = self.flight
        plots.plot_hover(path, fl.t, fl.throttle, fl.segments, fl.velocity_enu, fl.hover_estimate,
                         title=Path(fl.source).name)


# --------------------------------------------------------------------------- delay


@dataclass(frozen=True)
class DelayResult:
    """Command -> response delays (pair name, estimate), searched over the airborne window ``window_s`` [s]."""

    source: str
    window_s: tuple[float, float]
    mode: str
    estimates: list[tuple[str, DelayEstimate]]
    notes: list[str]
    block: dict = field(default_factory=dict)

    @property
    def report(self) -> dict:
        return {"kind": "delay", "source": self.source, "window_s": list(self.window_s), "mode": self.mode,
                "delays": {n: e.as_dict() for n, e in self.estimates}, "notes": self.notes}

    def summary_lines(self) -> list[str]:
        rows = [(n, f"{e.delay_s * 1e3:.1f}", f"[{e.ci_low_s * 1e3:.1f}, {e.ci_high_s * 1e3:.1f}]",
                 f"{e.peak_corr:+.3f}", e.label.split(": ", 1)[1]) for n, e in self.estimates]
        return _table(rows, ("pair", "delay_ms", "95% CI ms", "peak_r", "command -> response"))

    def plot(self, path: str) -> None:
        plots.plot_delays(path, [e for _, e in self.estimates], title=Path(self.source).name)


# --------------------------------------------------------------------------- regress


@dataclass(frozen=True)
class RegressionData:
    """The filtered airborne samples a regression used, at times ``t`` [s] (n,): specific force
    ``f`` [m/s^2], body velocity ``v_body`` [m/s], rates ``w`` [rad/s], angular acceleration
    ``w_dot`` [rad/s^2] (all (n, 3) FLU) and per-rotor thrust regressors ``thrust`` (n, N)."""

    t: np.ndarray
    f: np.ndarray
    v_body: np.ndarray
    w: np.ndarray
    w_dot: np.ndarray
    thrust: np.ndarray


@dataclass(frozen=True)
class RegressionResult:
    """Translational and rotational equation-error fits, their structural identifiability and, with a
    params file, the parameters they imply (``implied``; ``block`` holds those the schema accepts)."""

    source: str
    rate_hz: float
    lowpass_hz: float
    thrust_model: str
    intercept: bool
    geometry: RotorGeometry
    data: RegressionData
    translational: dict[str, LinearFit]
    rotational: dict[str, LinearFit]
    identified: list[str]
    structural: StructuralResult
    structural_known: StructuralResult | None
    params_source: str
    implied: dict[str, float]
    block: dict
    notes: list[str]

    @property
    def report(self) -> dict:
        return {"kind": "regress", "source": self.source, "n_samples": int(self.data.t.size),
                "rate_hz": self.rate_hz, "lowpass_hz": self.lowpass_hz, "thrust_model": self.thrust_model,
                "translational": {ax: f_.as_dict() for ax, f_ in self.translational.items()},
                "rotational": {ax: f_.as_dict() for ax, f_ in self.rotational.items()},
                "structural": self.structural.as_dict(),
                "structural_with_m_l_km_known": self.structural_known.as_dict() if self.structural_known else None,
                "implied": self.implied, "notes": self.notes}

    def summary_lines(self) -> list[str]:
        both = (("trans", self.translational), ("rot", self.rotational))
        rows = [(f"{eq} {ax}", nm, _g(fit.coef[i]), _g(fit.stderr[i], 2), f"{fit.t_values[i]:.1f}",
                 "yes" if fit.identifiable[i] else "NO", _g(fit.r2, 3), _g(fit.condition_number, 3))
                for eq, fits in both for ax, fit in fits.items() for i, nm in enumerate(fit.names)]
        lines = _table(rows, ("equation", "coefficient", "value", "stderr", "t", "ident.", "R2", "cond"))
        lines += [f"{ax}: only the combination {c.text()} = {_g(c.value)} +- {_g(c.stderr, 2)} is identifiable"
                  for _, fits in both for ax, fit in fits.items() for c in fit.combinations]
        lines.append("identified combinations (|t| >= 3): " + ", ".join(self.identified))
        lines += [f"not separately identifiable: {line}" for line in self.structural.describe()]
        known = self.structural_known
        if known is not None:
            lines.append(f"with m, l, km from {self.params_source}: separately identifiable: "
                         + (", ".join(known.determined) or "none")
                         + ("" if not known.null_directions else
                            "; still tied: " + "; ".join(", ".join(d) for d in known.null_directions)))
        lines += [f"implied (m, l, km from params): {k} = {_g(val)}" for k, val in self.implied.items()]
        return lines

    def plot(self, path: str) -> None:
        d = self.data
        cols_t = translational_columns(d.thrust, d.v_body, intercept=self.intercept)
        cols_r = rotational_columns(d.w, d.thrust, self.geometry, intercept=self.intercept)
        panels = [(f"f_{ax} [m/s2]", d.f[:, k], self.translational[ax].predict(cols_t[ax][0]),
                   self.translational[ax].r2) for ax, k in (("x", 0), ("y", 1), ("z", 2)) if ax in self.translational]
        panels += [(f"dw_{ax} [rad/s2]", d.w_dot[:, k], self.rotational[ax].predict(cols_r[ax][0]),
                    self.rotational[ax].r2) for ax, k in (("roll", 0), ("pitch", 1), ("yaw", 2))]
        plots.plot_regression(path, d.t, panels, title=Path(self.source).name)


# --------------------------------------------------------------------------- noise


@dataclass(frozen=True)
class NoiseResult:
    """IMU noise of the stationary ground stretch ``segment_s`` [s] (``n`` samples at ``rate_hz``)."""

    source: str
    segment_s: tuple[float, float]
    n: int
    rate_hz: float
    armed: bool
    imu: ImuNoise
    block: dict
    notes: list[str]

    @property
    def report(self) -> dict:
        return {"kind": "noise", "source": self.source, "segment_s": [float(v) for v in self.segment_s],
                "armed": bool(self.armed), "imu": self.imu.as_dict(), "notes": self.notes}

    def summary_lines(self) -> list[str]:
        d = self.imu.as_dict()
        rows = [(key, *(f"{x:.3e}" for x in d[key]), unit) for key, unit in (
            ("gyro_bias_rad_s", "rad/s"), ("gyro_noise_rad_s", "rad/s"),
            ("gyro_arw_rad_s_sqrt_hz", "rad/s/sqrt(Hz)"), ("gyro_bias_instability_rad_s", "rad/s"),
            ("accel_bias_m_s2", "m/s^2"), ("accel_noise_m_s2", "m/s^2"),
            ("accel_vrw_m_s2_sqrt_hz", "m/s^2/sqrt(Hz)"), ("accel_bias_instability_m_s2", "m/s^2"))]
        t0, t1 = self.segment_s
        return [f"stationary segment {t0:.2f}-{t1:.2f} s ({t1 - t0:.1f} s, {self.n} samples, "
                f"{self.rate_hz:.1f} Hz, {'armed' if self.armed else 'disarmed'}, landed)"] + \
            _table(rows, ("quantity", "x", "y", "z", "unit"))

    def plot(self, path: str) -> None:
        t0, t1 = self.segment_s
        plots.plot_allan(path, self.imu.gyro_allan, self.imu.accel_allan,
                         title=f"{Path(self.source).name}: {t0:.1f}-{t1:.1f} s")
