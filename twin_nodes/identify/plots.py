"""PNG figures for the identification results (matplotlib, Agg canvas, no pyplot state).

Every function takes results from the other ``twin_nodes.identify`` modules and
a path, draws on a fresh :class:`matplotlib.figure.Figure` with an Agg canvas
(so nothing depends on, or changes, the global backend) and writes the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def _save(fig: Figure, path: str | Path) -> None:
    FigureCanvasAgg(fig)
    fig.tight_layout()
    fig.savefig(str(path), dpi=110)


def plot_step_fit(path: str | Path, t_u: np.ndarray, u: np.ndarray, t_y: np.ndarray, y: np.ndarray,
                  fits: Mapping[str, object], *, y_label: str = "rotor speed [rpm]",
                  u_label: str = "command", title: str = "") -> None:
    """Measured vs fitted response (top), command (bottom), one line per fit in ``fits``."""
    fig = Figure(figsize=(10, 6))
    ax1 = fig.add_subplot(2, 1, 1)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax1)
    ax1.plot(t_y, y, ".", ms=2, color="0.5", label="measured")
    for name, fit in fits.items():
        yp = fit.predict(t_u, u, t_y)  # type: ignore[attr-defined]
        lab = (f"{name}: tau_up {fit.tau_up_s:.4g} s, tau_down {fit.tau_down_s:.4g} s, "  # type: ignore[attr-defined]
               f"K {fit.gain:.4g}, delay {fit.delay_s * 1e3:.1f} ms, R2 {fit.r2:.4f}")  # type: ignore[attr-defined]
        ax1.plot(t_y, yp, lw=1.2, label=lab)
    ax1.set_ylabel(y_label)
    ax1.legend(fontsize=7, loc="best")
    ax1.grid(alpha=0.3)
    ax2.step(t_u, u, where="post", lw=1.0)
    ax2.set_ylabel(u_label)
    ax2.set_xlabel("time [s]")
    ax2.grid(alpha=0.3)
    if title:
        ax1.set_title(title)
    _save(fig, path)


def plot_hover(path: str | Path, t: np.ndarray, throttle: np.ndarray, segments: Sequence[object],
               velocity_enu: np.ndarray | None = None, hover_estimate: np.ndarray | None = None,
               title: str = "") -> None:
    """Throttle over the flight with the detected hover segments shaded."""
    fig = Figure(figsize=(10, 6))
    ax1 = fig.add_subplot(2, 1, 1)
    ax1.plot(t, throttle, lw=0.8, label="throttle")
    if hover_estimate is not None:
        ax1.plot(t, hover_estimate, lw=0.8, label="PX4 hover thrust estimate")
    for s in segments:
        ax1.axvspan(s.t_start_s, s.t_end_s, color="tab:green", alpha=0.2)  # type: ignore[attr-defined]
        ax1.hlines(s.throttle_mean, s.t_start_s, s.t_end_s, color="k", lw=2)  # type: ignore[attr-defined]
    ax1.set_ylabel("throttle [-]")
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax1)
    if velocity_enu is not None:
        ax2.plot(t, velocity_enu[:, 2], lw=0.8, label="v up")
        ax2.plot(t, np.hypot(velocity_enu[:, 0], velocity_enu[:, 1]), lw=0.8, label="|v horizontal|")
        ax2.legend(fontsize=8)
    for s in segments:
        ax2.axvspan(s.t_start_s, s.t_end_s, color="tab:green", alpha=0.2)  # type: ignore[attr-defined]
    ax2.set_ylabel("speed [m/s]")
    ax2.set_xlabel("time [s]")
    ax2.grid(alpha=0.3)
    if title:
        ax1.set_title(title)
    _save(fig, path)


def plot_delays(path: str | Path, estimates: Sequence[object], title: str = "") -> None:
    """Normalised cross-correlation against lag for each delay estimate, peak marked."""
    n = max(1, len(estimates))
    fig = Figure(figsize=(10, 2.2 * n + 0.6))
    for i, e in enumerate(estimates):
        ax = fig.add_subplot(n, 1, i + 1)
        ax.plot(e.lags_s * 1e3, e.corr, lw=1.0)  # type: ignore[attr-defined]
        ax.axvline(e.delay_s * 1e3, color="r", lw=1)  # type: ignore[attr-defined]
        if np.isfinite(e.ci_low_s):  # type: ignore[attr-defined]
            ax.axvspan(e.ci_low_s * 1e3, e.ci_high_s * 1e3, color="r", alpha=0.15)  # type: ignore[attr-defined]
        ax.set_ylabel("corr")
        ax.set_title(f"{e.label}: {e.delay_s * 1e3:.1f} ms, peak {e.peak_corr:+.3f}", fontsize=9)  # type: ignore[attr-defined]
        ax.grid(alpha=0.3)
    if fig.axes:
        fig.axes[-1].set_xlabel("lag [ms] (response after command)")
        if title:
            fig.suptitle(title, fontsize=10)
    _save(fig, path)


def plot_regression(path: str | Path, t: np.ndarray, panels: Sequence[tuple[str, np.ndarray, np.ndarray, float]],
                    title: str = "") -> None:
    """Measured vs model-predicted signal per equation: ``(label, measured, predicted, r2)``."""
    n = max(1, len(panels))
    fig = Figure(figsize=(10, 1.9 * n + 0.6))
    for i, (label, meas, pred, r2) in enumerate(panels):
        ax = fig.add_subplot(n, 1, i + 1)
        ax.plot(t, meas, lw=0.7, color="0.4", label="measured")
        ax.plot(t, pred, lw=0.9, label=f"regression (R2 {r2:.3f})")
        ax.set_ylabel(label, fontsize=8)
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(alpha=0.3)
    if fig.axes:
        fig.axes[-1].set_xlabel("sample time [s] (airborne samples only)")
        if title:
            fig.suptitle(title, fontsize=10)
    _save(fig, path)


def plot_allan(path: str | Path, gyro: object, accel: object, title: str = "") -> None:
    """Log-log Allan deviation of gyro and accelerometer axes with the -1/2 random-walk lines."""
    fig = Figure(figsize=(10, 4.5))
    for j, (res, name, unit) in enumerate(((gyro, "gyro", "rad/s"), (accel, "accel", "m/s^2"))):
        ax = fig.add_subplot(1, 2, j + 1)
        taus = res.taus_s  # type: ignore[attr-defined]
        for k, axis in enumerate("xyz"):
            line, = ax.loglog(taus, res.adev[:, k], lw=1.2, label=f"{axis}")  # type: ignore[attr-defined]
            n_rw = res.random_walk[k]  # type: ignore[attr-defined]
            ax.loglog(taus, n_rw / np.sqrt(taus), "--", lw=0.8, color=line.get_color())
            b = res.bias_instability[k] * 0.664  # type: ignore[attr-defined]
            ax.plot(res.bias_instability_tau_s[k], b, "o", color=line.get_color())  # type: ignore[attr-defined]
        ax.set_xlabel("tau [s]")
        ax.set_ylabel(f"Allan deviation [{unit}]")
        ax.set_title(f"{name} (dashed: -1/2 slope, N at tau = 1 s)", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    _save(fig, path)
