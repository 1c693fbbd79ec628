"""The discovery result for people: the terminal summary, the HTML/PNG report, JSON conversion.

``summary_text(res)`` and ``write_report(folder, res, series)`` take what
:func:`twin_nodes.discovery.discover.discover` returns (``series`` is its ``"_series"`` entry);
``json_default`` makes numpy values JSON-serialisable (``json.dumps(res, default=json_default)``).
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from twin_nodes.discovery import locate


def _event_channels(e: dict) -> str:
    """``throttle -11σ, yaw +7σ``: an event's channels and their signed peaks."""
    return ", ".join(f"{c} {v['peak_sigma']:+.0f}σ" for c, v in e["channels"].items())


def _param_text(e: dict, name: str, value: float) -> str:
    """``name=value``; a parameter the fit held at nominal says so (not identified on this flight)."""
    held = (e.get("held_at_nominal") or {}).get(name)
    return f"{name}={value:.4g}" + (f" ({held})" if held else "")


def _not_identified(e: dict) -> list[str]:
    """A finding's parameters the flight did not identify: held at nominal, or (a ground effect, stages.ground)
    only one combination pinned by the low flight."""
    out = [f"              {k}: {why}" for k, why in (e.get("held_at_nominal") or {}).items()]
    if (e.get("ground_fit") or {}).get("determined") is False:
        out.append(f"              {e['ground_fit']['note']}")
    return out


def json_default(o):
    """``json.dumps`` fallback: numpy scalars and arrays as Python numbers and lists, anything else as str."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _alternative_lines(e: dict) -> list[str]:
    """The rivals a kept effect is not told apart from on this flight (the pair ``prove`` reads), one line each."""
    out = []
    for a in e.get("alternatives") or []:
        pretty = ", ".join(f"{k}={v:.4g}" for k, v in (a.get("params") or {}).items())
        cut = a.get("cv_improvement")
        cut = f", cross-validated cut {100 * cut:.0f} %" if isinstance(cut, (int, float)) else ""
        why = (a["note"] if a.get("note") else f"explains more, not yet significant: t {a.get('heldout_t_stat', 0):.1f}"
               if a.get("significant") is False else f"explains the same on this flight{cut}")
        out.append(f"              ~ {a['name']} {pretty} ({why})")
    return out


def summary_text(res: dict) -> str:
    """The terminal summary: worst mismatch windows, ranked candidates, verdict, closed-loop before/after."""
    lines = [f"discover: {res['log']}  (nominal {res['params']})",
             f"  fit on {res['method']['fit_interval_s']} s, judged on held-out {res['method']['heldout_interval_s']} s"]
    if res["mismatch"]:
        lines.append("  where the model and the flight disagree (worst window per channel):")
        worst: dict[tuple, dict] = {}
        for m in res["mismatch"]:
            key = (m["channel"], m.get("residual", "equation"))
            if key not in worst or m["severity"] > worst[key]["severity"]:
                worst[key] = m
        for m in sorted(worst.values(), key=lambda m: -m["severity"])[:8]:
            kind = "OE" if m.get("residual") == "output" else "EE"
            lines.append(f"    {m['channel']:<9} {kind} {m['t_start']:7.1f}-{m['t_end']:7.1f} s  {m['regime']:<28} "
                         f"severity {m['severity']:.1f}x {'typical error' if kind == 'OE' else 'noise'}")
    ev = res.get("events") or []
    if ev:
        lines.append(f"  short events the model does not explain (> {locate.EVENT_FACTOR:g} sigma of the flight's own "
                     f"residual and >= {100 * locate.EVENT_MIN_LEVEL:g} % of full output for >= {locate.EVENT_MIN_S:g} s; "
                     f"reported, not fitted):")
        for e in ev[:6]:
            lines.append(f"    {e['t_start']:7.2f}-{e['t_end']:7.2f} s  {_event_channels(e)}; vz {e['vz_m_s'][0]:+.1f}..{e['vz_m_s'][1]:+.1f} m/s"
                         f"{'; motors at full ' + str(e['motors_at_full']) if e['motors_at_full'] else ''}")
            lines.append(f"      -> {e['points_to']}")
    for a in res.get("authority") or []:
        lines.append(f"  mismatch located by the rate setpoint: {a['note']}")
    ex = res.get("excitation") or {}
    if ex:
        lines.append("  excitation (held-out blocks with signal / all; manoeuvres):")
        for ch in [c for c in ("throttle", "roll", "pitch", "yaw", "force_x", "force_y") if c in ex]:
            e = ex[ch]
            man = ", ".join(f"{k} {v}" for k, v in list(e["manoeuvres"].items())[:3]) or "-"
            lines.append(f"    {ch:<9} {e['blocks_heldout']:3d}/{e['blocks_heldout_total']:<3d} {man}")
    for n in res.get("not_excited") or []:
        lines.append(f"  not excited on this flight: {', '.join(n['effects'])} ({n['why']}); to show it fly {n['fly']}")
    lines.append("  candidates (verdict; held-out cut in its channel on the residual that judges it; the other "
                 "residual's cut):")
    for e in res["effects"][:8]:
        verdict = e.get("verdict") or ("confirmed" if e["accepted"] else "rejected")
        pretty = ", ".join(f"{k}={v:.4g}" for k, v in e["params"].items())
        kind = e.get("residual", "equation")
        other = [v for k, v in (e.get("residuals") or {}).items() if k != kind]
        o = ", ".join(f"{_KIND.get(r.get('residual'), '?')} {100 * r['heldout_improvement']:.0f} %"
                      for r in other if r.get("heldout_improvement") is not None)
        o = f"  [{o}]" if o else ""
        lines.append(f"    {verdict.upper():<9} {e['name']:<20} {_KIND.get(kind, 'EE')} "
                     f"{100 * e['heldout_improvement']:6.1f} % {e.get('heldout_channel', ''):<8}{o}  {pretty}")
        if verdict == "likely" or (verdict == "rejected" and "confirmation" in e):
            lines.append(f"              {e.get('verdict_note', '')}")
        if verdict != "rejected":
            lines += _not_identified(e) + _alternative_lines(e)
    after = res.get("confirmed_on_followup") or []
    if after:
        lines.append(f"  confirmed on the follow-up flight: {', '.join(after)}")
    if res["accepted"]:
        lines.append(f"  confirmed: {', '.join(res['accepted'])}")
    elif not after:
        lines.append("  confirmed: nothing (no candidate explains the held-out residual significantly)")
    if res.get("likely"):
        lines.append(f"  likely (fly the confirmation plan, then --confirm): {', '.join(res['likely'])}")
    conf = res.get("confirmation")
    if conf and conf.get("effects"):
        lines.append(f"  follow-up {conf['followup']}:")
        for r in conf["effects"]:
            lines.append(f"    {r['verdict'].upper():<9} {r['name']:<20} {r['note']}")
    from twin_nodes.discovery.stages.terms import summary_lines
    lines += summary_lines(res)
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


#: the residual an effect was judged on, as the summary abbreviates it (IV: the output error
#: projected on the rate setpoint, output_error.instrumented_inertia)
_KIND = {"equation": "EE", "output": "OE", "instrumented": "IV", "rate_loop": "RL"}


def _axes_text(res: dict) -> str:
    axes = (res.get("output_error_axes") or {}).get("axes")
    if not axes:
        return "output error not used on this flight"
    return "; ".join(f"{k} r\u00b2 {v['r2']:.2f} {'used' if v['used'] else 'left out'}" for k, v in axes.items())


def _plots(out: Path, res: dict, series: dict, plt) -> None:
    """``residuals.png`` (the equation error before/after) and ``candidates.png`` (the held-out cuts)."""
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
    colors = ["tab:green" if e["accepted"] else ("tab:orange" if e.get("verdict") == "likely" else "0.6")
              for e in eff]
    ax.barh([e["name"] for e in eff], vals, color=colors)
    ax.axvline(10, color="k", lw=0.6, ls="--")
    ax.invert_yaxis()
    ax.set_xlabel("held-out residual cut [%] (green = confirmed, orange = likely)")
    fig.tight_layout()
    fig.savefig(out / "candidates.png", dpi=90)
    plt.close(fig)


def _effect_rows(eff: list[dict]) -> str:
    """The candidates table's rows."""
    def verdict(e):
        v = e.get("verdict") or ("confirmed" if e["accepted"] else "rejected")
        return f"<b>{v}</b>" if v != "rejected" else v

    def resid(e):
        out = []
        for k, r in (e.get("residuals") or {}).items():
            if r.get("heldout_improvement") is None:
                continue
            out.append(f"{html.escape(k)}: {100 * r['heldout_improvement']:.0f} % in "
                       f"{html.escape(str(r['heldout_channel']))}")
        return "<br>".join(out)

    def excit(e):
        x = e.get("excitation") or {}
        if not x:
            return ""
        s = (f"{html.escape(str(x.get('channel')))}: {x.get('blocks_heldout', '?')}/{x.get('blocks_heldout_total', '?')}"
             f" held-out blocks excited")
        if x.get("blocks_missing"):
            s += f"; ~{x['blocks_missing']} more needed: {html.escape(x.get('supplied_by', ''))}"
        return s
    rows = "".join(
        f"<tr><td>{verdict(e)}</td><td>{html.escape(e['name'])}</td>"
        f"<td>{html.escape(', '.join(_param_text(e, k, v) for k, v in e['params'].items()))}</td>"
        f"<td>{e['heldout_before']:.4f}</td><td>{e['heldout_after']:.4f}</td><td>{resid(e)}</td><td>{excit(e)}</td>"
        f"<td>{html.escape(e['evidence'])} {html.escape(e.get('verdict_note', '') if e.get('verdict') == 'likely' else '')}"
        f"</td></tr>" for e in eff)
    return rows


def _events_html(res: dict) -> str:
    """The short events section ('' without events)."""
    evrows = "".join(
        f"<tr><td>{e['t_start']}–{e['t_end']} s</td><td>{html.escape(_event_channels(e))}</td>"
        f"<td>{e['vz_m_s'][0]:+.1f}..{e['vz_m_s'][1]:+.1f}</td><td>{e['height_m']}</td><td>{e['motors_at_full'] or ''}</td>"
        f"<td>{html.escape(e['points_to'])}</td></tr>" for e in res.get("events") or [])
    evsec = ("<h2>Short events the model does not explain</h2><p>Spans of at least "
             f"{locate.EVENT_MIN_S:g} s where the collective or a moment mode of the residual leaves "
             f"{locate.EVENT_FACTOR:g}x its own flight-long robust spread by at least {100 * locate.EVENT_MIN_LEVEL:g} % of "
             "full output: reported with what the vehicle did, not fitted.</p>"
             "<table><tr><th>when</th><th>channels (peak)</th><th>vz m/s</th><th>height m</th><th>motors at full</th>"
             f"<th>points to</th></tr>{evrows}</table>") if evrows else ""
    return evsec


def write_report(folder, res: dict, series: dict) -> None:
    """Plots of the residual before/after on the held-out part and the candidate ranking, plus index.html."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    _plots(out, res, series, plt)

    rl = _rate_loop_plot(out, res, plt)

    rows = _effect_rows(res["effects"])
    ex = res.get("excitation") or {}
    exrows = "".join(f"<tr><td>{html.escape(ch)}</td><td>{v['blocks_heldout']}/{v['blocks_heldout_total']}</td>"
                     f"<td>{v['blocks_flight']}/{v['blocks_flight_total']}</td><td>"
                     f"{html.escape(', '.join(f'{k} {n}' for k, n in v['manoeuvres'].items()))}</td></tr>"
                     for ch, v in ex.items())
    mm = "".join(f"<tr><td>{m['channel']}</td><td>{m.get('residual', 'equation')}</td><td>{m['t_start']}–{m['t_end']} s"
                 f"</td><td>{html.escape(m['regime'])}</td><td>{m['severity']}</td></tr>" for m in res["mismatch"][:20])
    evsec = _events_html(res)
    head = (f"Confirmed: <b>{', '.join(res['accepted'])}</b>" if res["accepted"]
            else "Nothing confirmed: no candidate explains the held-out residual significantly.")
    if res.get("likely"):
        head += f" Likely (needs a confirmation flight): <b>{', '.join(res['likely'])}</b>."
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>rotortwin discover</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:auto}} td,th{{border-bottom:1px solid #ddd;padding:3px 6px;font-size:13px}}</style></head>
<body><h1>Missing-physics discovery</h1><p>{html.escape(res['log'])} with {html.escape(str(res['params']))}</p>
<h2>{head}</h2>
<p>Residual = what the log measured minus what the model predicts from the logged motor commands, per motor and as horizontal force,
in fraction of full motor output (the <i>equation error</i>); the <i>output error</i> flies the model open loop from the logged state for
short horizons on the logged commands and compares body rates and vertical velocity, in the same channels, each axis
in units of the nominal model's typical error on it ({html.escape(_axes_text(res))}). Fit on {res['method']['fit_interval_s']} s, judged on {res['method']['heldout_interval_s']} s.
{html.escape(res['method']['acceptance'])}.</p>
<img src="residuals.png" width="100%"><h2>Candidates</h2><img src="candidates.png">
<table><tr><th>verdict</th><th>effect</th><th>parameters</th><th>held-out before</th><th>after</th><th>both residuals (held-out cut)</th><th>excitation</th><th>evidence</th></tr>{rows}</table>
{rl}
<h2>Excitation per channel</h2><p>Blocks (0.5 s) whose commanded signal in the channel is above 3x its noise floor, on the held-out parts and over the flight, and the manoeuvres they come from.</p>
<table><tr><th>channel</th><th>held-out</th><th>flight</th><th>manoeuvres (held-out)</th></tr>{exrows}</table>
<h2>Where the mismatch is</h2><table><tr><th>channel</th><th>residual</th><th>when</th><th>regime</th><th>severity (x noise; output error: x typical error)</th></tr>{mm}</table>
{evsec}
</body></html>"""
    (out / "index.html").write_text(page)


def _rate_loop_plot(out: Path, res: dict, plt) -> str:
    """``rate_loop.png``: how well PX4's rate loop flown on the model fits the logged body rates against
    each axis's inertia scale (and the motors' lag, where it was read), and the HTML that shows it; ''
    when the rate loop was not flown (not a PX4 log)."""
    ins = res.get("instrumented") or {}
    lag = res.get("rate_loop_lag") or {}
    curve, lcurve = ins.get("curve") if ins.get("method") == "rate_loop" else None, lag.get("curve")
    if not curve:
        return ""
    n = 2 if lcurve else 1
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 3.4))
    axes = np.atleast_1d(axes)
    for a in ("roll", "pitch", "yaw"):
        if a in curve:
            axes[0].plot(curve["scales"], curve[a], label=a)
    axes[0].axvline(1.0, color="k", lw=0.6, ls="--")
    axes[0].set_xscale("log")
    axes[0].set_xlabel("inertia / model's")
    axes[0].set_ylabel("sum of squares / its minimum")
    axes[0].set_ylim(0.99, 1.15)
    axes[0].legend(fontsize=8)
    axes[0].set_title("body rate, PX4's rate loop on the model", fontsize=9)
    if lcurve:
        for a in ("roll", "pitch", "yaw"):
            axes[1].plot(lcurve["taus"], lcurve[a], label=a)
        axes[1].axvline(lag["model_tau"], color="k", lw=0.6, ls="--")
        axes[1].set_xscale("log")
        axes[1].set_xlabel("motor time constant [s]")
        axes[1].set_ylim(0.99, 1.15)
        axes[1].legend(fontsize=8)
        axes[1].set_title(f"the motors' lag: {lag['tau']:.3f} s (model {lag['model_tau']:.3f})", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "rate_loop.png", dpi=90)
    plt.close(fig)
    return ("<h2>PX4's rate loop flown on the model</h2><p>The log's rate-loop gains and filters on the model, driven by "
            "the logged rate setpoint (no motor command), compared with the logged body rates in "
            f"{ins.get('window_s', 1)} s windows; each curve's minimum is what the flight reads, the dashed line the "
            "model's value. " + html.escape("; ".join(str(x) for x in (ins.get("why_not") or []))) + "</p>"
            '<img src="rate_loop.png">')


__all__ = ["json_default", "summary_text", "write_report"]
