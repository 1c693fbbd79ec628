"""A one-page twin-versus-real report: PNG plots and an index.html (matplotlib Agg).

``write_report(out_dir, aligned, metrics)`` writes:

- ``xy.png`` the horizontal track, twin over real;
- ``z.png`` altitude; ``throttle.png`` collective throttle; ``motors.png`` one
  panel per motor;
- ``errors.png`` the errors over time (XY distance, Z, throttle) with a 5 s
  rolling RMSE;
- ``index.html`` the Table-2 numbers, what they mean, and the plots.

Grey bands mark samples that are not counted (on the ground).
"""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from twin_nodes.twin.metrics import Aligned, channel_errors, table2

__all__ = ["write_report"]

TWIN, REAL = "#d62728", "#1f77b4"


def _plt() -> Any:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _shade(ax: Any, t: np.ndarray, mask: np.ndarray) -> None:
    """Grey spans where ``mask`` is False."""
    if t.size == 0:
        return
    off = ~mask
    edges = np.flatnonzero(np.diff(np.concatenate([[0], off.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        ax.axvspan(t[a], t[min(b, len(t) - 1)], color="0.9", lw=0)


def _rolling_rms(t: np.ndarray, e: np.ndarray, window_s: float = 5.0) -> np.ndarray:
    ok = np.isfinite(e)
    e2 = np.where(ok, e * e, 0.0)
    c = np.concatenate([[0.0], np.cumsum(e2)])
    n = np.concatenate([[0], np.cumsum(ok)])
    j = np.searchsorted(t, t - window_s, side="right")
    i = np.arange(len(t)) + 1
    cnt = n[i] - n[j]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt((c[i] - c[j]) / np.maximum(cnt, 1)), np.nan)


def write_report(out_dir: str | Path, al: Aligned | None, metrics: Mapping[str, Any], title: str = "") -> Path:
    """Write the plots and ``index.html`` into ``out_dir``; returns the index path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plt = _plt()
    figs: list[tuple[str, str]] = []
    if al is not None and len(al.t):
        t = al.t - al.t[0]
        mask = np.asarray(al.mask, bool)

        fig, ax = plt.subplots(figsize=(6.5, 6))
        ax.plot(al.xy_real[:, 0], al.xy_real[:, 1], color=REAL, label="real (EKF)")
        ax.plot(al.xy_twin[:, 0], al.xy_twin[:, 1], color=TWIN, ls="--", label="twin")
        ax.set_xlabel("east [m]")
        ax.set_ylabel("north [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend()
        ax.set_title(f"XY track: RMSE {metrics.get('xy_rmse_m', math.nan):.2f} m, "
                     f"P75 {metrics.get('xy_p75_m', math.nan):.2f} m")
        fig.tight_layout()
        fig.savefig(out / "xy.png", dpi=90)
        plt.close(fig)
        figs.append(("xy.png", "Horizontal track seen from above (ENU: x east, y north)."))

        for name, real, twin, ylabel, key, unit, scale in (
                ("z.png", al.z_real, al.z_twin, "altitude z (ENU up) [m]", "z", "m", 1.0),
                ("throttle.png", al.throttle_real, al.throttle_twin, "collective throttle [%]", "throttle", "%",
                 100.0)):
            fig, ax = plt.subplots(figsize=(10, 3.2))
            _shade(ax, t, mask)
            ax.plot(t, real * scale, color=REAL, lw=1, label="real")
            ax.plot(t, twin * scale, color=TWIN, lw=1, label="twin")
            ax.set_xlabel("time [s]")
            ax.set_ylabel(ylabel)
            ax.legend(loc="upper right")
            sfx = "_m" if unit == "m" else ""
            ax.set_title(f"{key}: RMSE {metrics.get(f'{key}_rmse{sfx}', math.nan) * scale:.2f} {unit}, "
                         f"P75 {metrics.get(f'{key}_p75{sfx}', math.nan) * scale:.2f} {unit}")
            fig.tight_layout()
            fig.savefig(out / name, dpi=90)
            plt.close(fig)
        figs.append(("z.png", "Altitude over time; grey = on the ground (not counted)."))
        figs.append(("throttle.png", "Collective throttle: real = PX4 thrust setpoint, twin = its controller's."))

        n = al.n_motors
        fig, axes = plt.subplots(n, 1, figsize=(10, 1.9 * n + 0.6), sharex=True, squeeze=False)
        p75 = metrics.get("motor_p75", [math.nan] * n)
        for i in range(n):
            ax = axes[i, 0]
            _shade(ax, t, mask)
            ax.plot(t, al.motors_real[:, i] * 100, color=REAL, lw=0.8, label="real")
            ax.plot(t, al.motors_twin[:, i] * 100, color=TWIN, lw=0.8, label="twin")
            ax.set_ylabel(f"M{i + 1} [%]")
            ax.text(0.01, 0.85, f"P75 {p75[i] * 100:.1f} %", transform=ax.transAxes, fontsize=8)
        axes[0, 0].legend(loc="upper right", fontsize=8)
        axes[-1, 0].set_xlabel("time [s]")
        fig.suptitle("Motor commands (PX4 order, 0..100 %)")
        fig.tight_layout()
        fig.savefig(out / "motors.png", dpi=90)
        plt.close(fig)
        figs.append(("motors.png", "Each motor's command; Motor1 = PX4 actuator_motors.control[0]."))

        err = channel_errors(Aligned(t=al.t, xy_twin=al.xy_twin, xy_real=al.xy_real, z_twin=al.z_twin,
                                     z_real=al.z_real, throttle_twin=al.throttle_twin,
                                     throttle_real=al.throttle_real, motors_twin=al.motors_twin,
                                     motors_real=al.motors_real, mask=np.ones(len(al.t), bool)))
        fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
        for ax, key, lab, sc in ((axes[0], "xy", "XY distance [m]", 1.0), (axes[1], "z", "Z error [m]", 1.0),
                                 (axes[2], "throttle", "throttle error [%]", 100.0)):
            e = err[key] * sc
            _shade(ax, t, mask)
            ax.plot(t, e, color="0.4", lw=0.7, label="twin - real")
            ax.plot(t, _rolling_rms(t, np.where(mask, e, np.nan)), color="k", lw=1.5, label="5 s rolling RMSE")
            ax.axhline(0, color="0.7", lw=0.5)
            ax.set_ylabel(lab)
        axes[0].legend(loc="upper right", fontsize=8)
        axes[-1].set_xlabel("time [s]")
        fig.tight_layout()
        fig.savefig(out / "errors.png", dpi=90)
        plt.close(fig)
        figs.append(("errors.png", "The errors over time and their 5 s rolling RMSE (airborne only)."))

    text = table2(metrics, title=f"Twin vs real: {title}" if title else "")
    rows = "".join(f"<figure><img src='{f}' alt='{f}'><figcaption>{html.escape(c)}</figcaption></figure>"
                   for f, c in figs)
    notes = "".join(f"<li>{html.escape(str(n))}</li>" for n in metrics.get("notes", []) or [])
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>rotortwin report {html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1050px;margin:1em auto;color:#222}}
pre{{background:#f4f4f4;padding:.8em;font-size:14px}} img{{max-width:100%}} figure{{margin:1.2em 0}}
figcaption{{color:#555;font-size:13px}}</style></head><body>
<h1>Twin vs real: {html.escape(title)}</h1>
<p>The digital twin (<b>{html.escape(str(metrics.get('params', metrics.get('params_file', ''))))}</b>,
<b>{html.escape(str(metrics.get('mode', '')))}</b> loop) ran beside the logged flight. Errors are twin minus
real on a {metrics.get('rate_hz', 50):.0f} Hz grid, counted only while airborne. RMSE = root mean square;
P75 / median = 75th / 50th percentile of the absolute error; throttle and motor errors are in percentage points
of the 0..100 % command. <span style="color:{REAL}">Blue = real</span>,
<span style="color:{TWIN}">red = twin</span>.</p>
<pre>{html.escape(text)}</pre>
{f'<ul>{notes}</ul>' if notes else ''}
{rows}
<p style="color:#777;font-size:12px">Definitions: {html.escape(str(metrics.get('definitions', '')))}</p>
</body></html>"""
    idx = out / "index.html"
    idx.write_text(page, encoding="utf-8")
    return idx
