"""``rotortwin discover`` and ``rotortwin prove``."""

from __future__ import annotations

import html
import json
import os
import sys
from pathlib import Path

import numpy as np


def register(sub) -> None:
    p = sub.add_parser("discover", help="locate the twin/real mismatch, name the missing physics, refit, "
                                        "show the held-out improvement")
    p.add_argument("flight", help="PX4 ULog (.ulg)")
    p.add_argument("--params", required=True, help="nominal vehicle params YAML")
    p.add_argument("--json", dest="json_out", help="write the result here")
    p.add_argument("--report", help="write plots and index.html into this folder")
    p.add_argument("--out-params", help="write the refitted params YAML here (when something is accepted)")
    p.add_argument("--heldout", type=float, default=0.35, help="fraction of the flight held out (default 0.35)")
    p.add_argument("--no-closed-loop", action="store_true", help="skip the closed-loop twin before/after metrics")
    p.set_defaults(func=_discover)

    q = sub.add_parser("prove", help="fly our own flights with one hidden effect each and find them blind")
    q.add_argument("--out", default="out/prove", help="folder for the flights (ULog), results and table")
    q.add_argument("--vehicle", default="px4_sih_quadx", help="shipped params name or a params YAML")
    q.add_argument("--size", choices=("full", "ci"), default="full")
    q.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    q.set_defaults(func=_prove)

    s = sub.add_parser("simulate", help="fly the shipped mission with our simulator (optionally with a hidden "
                                        "effect) and write it as a PX4 ULog")
    s.add_argument("--params", default="params/px4_sih_quadx.yaml", help="vehicle params YAML")
    s.add_argument("--effect", default="none",
                   help="hidden effect, e.g. 'motor_efficiency:motor=3,efficiency=0.85' (default none)")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--out", required=True, help="output .ulg")
    s.set_defaults(func=_simulate)


def _discover(args) -> int:
    from twin_nodes.discovery.discover import discover
    from twin_nodes.params import load_params, write_params
    from twin_nodes.ulog_io import read_ulog

    vp = load_params(args.params)
    log = read_ulog(args.flight)
    res = discover(log, vp, heldout_fraction=args.heldout, progress=sys.stderr.isatty(),
                   closed_loop_metrics=not args.no_closed_loop)
    series = res.pop("_series")
    print(summary_text(res))
    if args.json_out:
        _atomic_write(args.json_out, json.dumps(res, indent=1, default=_json_default))
        print(f"result: {args.json_out}")
    if args.report:
        write_report(args.report, res, series)
        print(f"report: {Path(args.report) / 'index.html'}")
    if args.out_params and res["accepted"]:
        from twin_nodes.params import from_ros_dict
        new = from_ros_dict(res["refit_params"], args.out_params)
        write_params(new, args.out_params, header=f"refitted by rotortwin discover on {args.flight}: "
                                                   f"added {', '.join(res['accepted'])}")
        print(f"refitted params: {args.out_params}")
    return 0


def _prove(args) -> int:
    from twin_nodes.discovery.prove import format_table, run_suite

    summary = run_suite(args.out, args.vehicle, args.size, args.workers)
    table = format_table(summary)
    print(table)
    out = Path(args.out)
    _atomic_write(out / "summary.json", json.dumps(summary, indent=1, default=_json_default))
    _atomic_write(out / "table.txt", table + "\n")
    print(f"flights, per-flight results and summary: {out}")
    return 0


def parse_effect(spec: str):
    """'name:k=v,k=v' -> Hidden; raises TwinError on a bad spec."""
    from twin_nodes.discovery.prove import Hidden
    from twin_nodes.errors import TwinError
    from twin_nodes.physics.effects import EFFECTS

    if spec in ("", "none"):
        return Hidden("none", {})
    name, _, rest = spec.partition(":")
    if name not in EFFECTS:
        raise TwinError(f"--effect: {name!r}: expected one of {', '.join(sorted(EFFECTS))}")
    params = {}
    for item in filter(None, rest.split(",")):
        k, eq, v = item.partition("=")
        if not eq or k not in EFFECTS[name].param_names:
            raise TwinError(f"--effect: {item!r}: expected k=v with k in {list(EFFECTS[name].param_names)}")
        try:
            params[k] = float(v)
        except ValueError:
            raise TwinError(f"--effect: {k}: expected a number, got {v!r}") from None
    return Hidden(name, params)


def _simulate(args) -> int:
    from twin_nodes.discovery.prove import write_flight
    from twin_nodes.params import load_params

    vp = load_params(args.params)
    hidden = parse_effect(args.effect)
    facts = write_flight(args.out, vp, hidden, args.seed)
    print(f"wrote {args.out}: {facts['duration_s']:.0f} s, hidden effect {hidden.name} {hidden.params}, "
          f"XY tracking RMSE {facts['xy_tracking_rmse_m']:.2f} m, Z {facts['z_tracking_rmse_m']:.2f} m")
    return 0


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _atomic_write(path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def summary_text(res: dict) -> str:
    lines = [f"discover: {res['log']}  (nominal {res['params']})",
             f"  fit on {res['method']['fit_interval_s']} s, judged on held-out {res['method']['heldout_interval_s']} s"]
    if res["mismatch"]:
        lines.append("  where the model and the flight disagree (worst window per channel):")
        worst: dict[str, dict] = {}
        for m in res["mismatch"]:
            if m["channel"] not in worst or m["severity"] > worst[m["channel"]]["severity"]:
                worst[m["channel"]] = m
        for m in sorted(worst.values(), key=lambda m: -m["severity"])[:6]:
            lines.append(f"    {m['channel']:<9} {m['t_start']:7.1f}-{m['t_end']:7.1f} s  {m['regime']:<28} "
                         f"severity {m['severity']:.1f}x noise")
    lines.append("  candidates (ranked by held-out improvement):")
    for e in res["effects"][:8]:
        mark = "ACCEPT" if e["accepted"] else "      "
        pretty = ", ".join(f"{k}={v:.4g}" for k, v in e["params"].items())
        lines.append(f"    {mark} {e['name']:<20} {100 * e['heldout_improvement']:6.1f} %  {pretty}")
    if res["accepted"]:
        lines.append(f"  accepted: {', '.join(res['accepted'])}")
    else:
        lines.append("  accepted: nothing (no candidate explains the held-out residual significantly)")
    cl = res.get("after", {}).get("closed_loop_heldout")
    cb = res.get("baseline", {}).get("closed_loop_heldout")
    if isinstance(cl, dict) and isinstance(cb, dict):
        lines.append("  closed-loop twin on the held-out part (before -> after):")
        for k in ("xy_rmse_m", "z_rmse_m", "throttle_rmse"):
            if k in cb and k in cl:
                lines.append(f"    {k:<14} {cb[k]:.4f} -> {cl[k]:.4f}")
        if "motor_rmse" in cb and "motor_rmse" in cl:
            lines.append("    motor_rmse     " + " ".join(f"{a:.3f}->{b:.3f}" for a, b in
                                                         zip(cb["motor_rmse"], cl["motor_rmse"])))
    return "\n".join(lines)


def write_report(folder, res: dict, series: dict) -> None:
    """Plots of the residual before/after on the held-out part and the candidate ranking, plus index.html."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    t, valid, held = series["t"], series["valid"], series["held"]
    Rb, Ra, names = series["R_before"], series["R_after"], series["names"]
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 1.6 * len(names) + 1), sharex=True)
    for i, ax in enumerate(np.atleast_1d(axes)):
        rb = np.where(valid, Rb[:, i], np.nan)
        ra = np.where(valid, Ra[:, i], np.nan)
        ax.plot(t, rb, color="tab:red", lw=0.8, label="before")
        ax.plot(t, ra, color="tab:green", lw=0.8, label="after")
        ax.axvspan(t[held][0] if held.any() else t[-1], t[-1], color="0.9", zorder=-1)
        ax.set_ylabel(names[i], fontsize=8)
        ax.axhline(0, color="k", lw=0.5)
    np.atleast_1d(axes)[0].legend(loc="upper right", fontsize=8)
    np.atleast_1d(axes)[0].set_title("equation-error residual (fraction of full motor output); grey = held out")
    np.atleast_1d(axes)[-1].set_xlabel("time since log start [s]")
    fig.tight_layout()
    fig.savefig(out / "residuals.png", dpi=90)
    plt.close(fig)

    eff = res["effects"]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(eff) + 1.2))
    vals = [100 * e["heldout_improvement"] for e in eff]
    colors = ["tab:green" if e["accepted"] else "0.6" for e in eff]
    ax.barh([e["name"] for e in eff], vals, color=colors)
    ax.axvline(10, color="k", lw=0.6, ls="--")
    ax.invert_yaxis()
    ax.set_xlabel("held-out residual cut [%] (green = accepted)")
    fig.tight_layout()
    fig.savefig(out / "candidates.png", dpi=90)
    plt.close(fig)

    rows = "".join(
        f"<tr><td>{'<b>accepted</b>' if e['accepted'] else ''}</td><td>{html.escape(e['name'])}</td>"
        f"<td>{html.escape(', '.join(f'{k}={v:.4g}' for k, v in e['params'].items()))}</td>"
        f"<td>{e['heldout_before']:.4f}</td><td>{e['heldout_after']:.4f}</td>"
        f"<td>{html.escape(e['evidence'])}</td></tr>" for e in eff)
    mm = "".join(f"<tr><td>{m['channel']}</td><td>{m['t_start']}–{m['t_end']} s</td><td>{html.escape(m['regime'])}"
                 f"</td><td>{m['severity']}</td></tr>" for m in res["mismatch"][:15])
    verdict = (f"Found: <b>{', '.join(res['accepted'])}</b>" if res["accepted"]
               else "Nothing accepted: no candidate explains the held-out residual significantly.")
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>rotortwin discover</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:auto}} td,th{{border-bottom:1px solid #ddd;padding:3px 6px;font-size:13px}}</style></head>
<body><h1>Missing-physics discovery</h1><p>{html.escape(res['log'])} with {html.escape(str(res['params']))}</p>
<h2>{verdict}</h2>
<p>Residual = what the log measured minus what the model predicts from the logged motor commands, per motor and as horizontal force,
in fraction of full motor output. Fit on {res['method']['fit_interval_s']} s, judged on {res['method']['heldout_interval_s']} s.
{html.escape(res['method']['acceptance'])}.</p>
<img src="residuals.png" width="100%"><h2>Candidates</h2><img src="candidates.png">
<table><tr><th></th><th>effect</th><th>parameters</th><th>held-out before</th><th>after</th><th>evidence</th></tr>{rows}</table>
<h2>Where the mismatch is</h2><table><tr><th>channel</th><th>when</th><th>regime</th><th>severity (x noise)</th></tr>{mm}</table>
</body></html>"""
    (out / "index.html").write_text(page)
