"""``rotortwin identify``: the second reference's parameter identification from data.

::

    rotortwin identify motor   STEPS.csv|LOG.ulg [--rate-hz 30] [--no-delay] [--symmetric]
    rotortwin identify hover   LOG.ulg [--mass-kg M] [--min-duration 3]
    rotortwin identify delay   LOG.ulg [--pairs thrust,torque_roll,...]
    rotortwin identify regress LOG.ulg [--rate-hz 50] [--lowpass-hz 4] [--tau-s 0.05]
    rotortwin identify noise   LOG.ulg [--allow-armed] [--accel-reference mean_direction|level]

Every subcommand also takes ``--params P.yaml`` (vehicle parameters: mass, rotor
geometry, command map), ``--out OUT.yaml|OUT.json`` and ``--plot OUT.png``.

The output file holds two top-level keys: ``/**: {ros__parameters: {...}}``
with only parameter-file keys (merge it into a params file: ``rotors.tau_up_s``/
``tau_down_s`` from ``motor``; ``rotors.kt_n_s2_rad2`` from ``hover`` where RPM is
logged, else with ``--params`` the file's ``thrust_max_n``/``kt`` that hovers at
the measured command; from ``regress`` with ``--params`` the thrust parameter and
``vehicle.ixx/iyy/izz_kg_m2`` implied by the params file's mass, arm length and
km, for coefficients with |t| >= 20; the ``sensors`` block from ``noise``; nothing
from ``delay``), and ``identify: {...}`` with the full report (all numbers,
standard errors, segments, notes; the hover throttle is there).  With ``--params`` the merged result is validated by
``twin_nodes.params.from_ros_dict`` before anything is written.

Motor CSV format: a header row with columns ``time_s,command,rpm`` (see
:mod:`twin_nodes.identify.step_response`).

Bad input raises :class:`~twin_nodes.errors.LogError` / ``ParamsError`` with a
one-line message; every result is computed and checked before any file is
written, so a failure leaves nothing behind.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import math
import os
import shlex
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import yaml

from twin_nodes.errors import LogError, ParamsError

OUT_SUFFIXES = (".yaml", ".yml", ".json")


# =========================================================================== registration


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("identify", help="identify motor lag, hover thrust, delays, model coefficients, IMU noise",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="identify_command", metavar="WHAT")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    m = sub.add_parser("motor", help="first-order motor model K/(tau s+1) (+delay) from command/rpm steps")
    m.add_argument("source", help="CSV with time_s,command,rpm columns, or a ULog with esc_status RPM")
    m.add_argument("--rate-hz", type=float, default=30.0,
                   help="rate of the ZOH difference equation (reference: 30 Hz PWM logging)")
    m.add_argument("--no-delay", action="store_true", help="do not fit a pure delay")
    m.add_argument("--max-delay", type=float, default=0.5, help="largest delay to consider [s]")
    m.add_argument("--symmetric", action="store_true",
                   help="write the symmetric tau as both tau_up_s and tau_down_s")
    _common(m)
    m.set_defaults(func=_cmd_motor)

    h = sub.add_parser("hover", help="hover throttle from steady-hover segments; kt = m g / (N w^2) with RPM")
    h.add_argument("log", help="ULog")
    h.add_argument("--mass-kg", type=float, help="vehicle mass (else from --params)")
    h.add_argument("--min-duration", type=float, default=3.0, help="shortest hover segment [s]")
    h.add_argument("--max-vz", type=float, default=0.3, help="largest vertical speed in hover [m/s]")
    h.add_argument("--max-vxy", type=float, default=0.5, help="largest horizontal speed in hover [m/s]")
    h.add_argument("--max-az", type=float, default=0.5, help="largest vertical acceleration [m/s^2]")
    h.add_argument("--min-height", type=float, default=1.0, help="smallest height above the take-off point [m]")
    _common(h)
    h.set_defaults(func=_cmd_hover)

    d = sub.add_parser("delay", help="command -> response delays by cross-correlation")
    d.add_argument("log", help="ULog")
    d.add_argument("--pairs", help=f"comma-separated subset of: {', '.join(DELAY_PAIRS)} (default: all available)")
    d.add_argument("--mode", choices=("level", "diff"), default="level",
                   help="correlate detrended levels or first differences")
    d.add_argument("--highpass-s", type=float, default=1.0,
                   help="remove a moving average this long from both series first (0: off; not for 'climb')")
    d.add_argument("--boot", type=int, default=300, help="bootstrap replicates for the 95 %% interval")
    _common(d)
    d.set_defaults(func=_cmd_delay)

    r = sub.add_parser("regress", help="equation-error least squares of translational and rotational dynamics")
    r.add_argument("log", help="ULog")
    r.add_argument("--rate-hz", type=float, default=50.0, help="resampling rate [Hz]")
    r.add_argument("--lowpass-hz", type=float,
                   help="zero-phase low-pass applied to both sides (default: 0.4 x the motor log rate, <= 8 Hz)")
    r.add_argument("--tau-s", type=float, default=0.05,
                   help="motor time constant when no --params is given [s]")
    r.add_argument("--trim-s", type=float, default=2.0,
                   help="drop this much after take-off and before touchdown (ground contact) [s]")
    r.add_argument("--accel-source", choices=("rates", "px4"), default="rates",
                   help="angular acceleration from differentiated body rates or PX4's xyz_derivative")
    r.add_argument("--intercept", action="store_true", help="add a constant term to every equation")
    r.add_argument("--rcond", type=float, default=1e-3,
                   help="relative singular-value threshold below which a direction counts as unidentifiable")
    _common(r)
    r.set_defaults(func=_cmd_regress)

    n = sub.add_parser("noise", help="IMU bias, white noise and Allan deviation from the pre-arm ground segment")
    n.add_argument("log", help="ULog")
    n.add_argument("--allow-armed", action="store_true",
                   help="if there is no landed+disarmed stretch, use landed+armed (motor vibration included)")
    n.add_argument("--min-duration", type=float, default=3.0, help="shortest stationary stretch [s]")
    n.add_argument("--gyro-std-max", type=float, default=0.02,
                   help="stationary: largest 1 s moving std of each gyro axis [rad/s]")
    n.add_argument("--accel-std-max", type=float, default=0.15,
                   help="stationary: largest 1 s moving std of the accelerometer magnitude [m/s^2]")
    n.add_argument("--accel-reference", choices=("mean_direction", "level"), default="mean_direction",
                   help="what the accelerometer should read at rest (see twin_nodes.identify.noise)")
    _common(n)
    n.set_defaults(func=_cmd_noise)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--params", help="vehicle params YAML (mass, rotor geometry, command map)")
    p.add_argument("--out", help="write the result here (.yaml/.yml or .json)")
    p.add_argument("--plot", help="write a PNG figure here")


# =========================================================================== shared plumbing


def _check_out_paths(args: argparse.Namespace) -> None:
    if args.out:
        suf = Path(args.out).suffix.lower()
        if suf not in OUT_SUFFIXES:
            raise ParamsError(args.out, "--out", f"expected a file name ending in {', '.join(OUT_SUFFIXES)}, got {suf or 'no suffix'!r}")
        if not Path(args.out).resolve().parent.is_dir():
            raise ParamsError(args.out, "--out", "expected an existing directory to write into")
    if args.plot:
        if Path(args.plot).suffix.lower() != ".png":
            raise ParamsError(args.plot, "--plot", "expected a .png file name")
        if not Path(args.plot).resolve().parent.is_dir():
            raise ParamsError(args.plot, "--plot", "expected an existing directory to write into")


def _load_vp(args: argparse.Namespace) -> Any:
    if not getattr(args, "params", None):
        return None
    from twin_nodes.params import load_params
    return load_params(args.params)


def _read_log(path: str) -> Any:
    from twin_nodes.ulog_io import read_ulog
    return read_ulog(path)


def _deep_merge(base: dict, block: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in block.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def merge_into_params(base_ros: dict, block: dict) -> dict:
    """``base_ros`` (a ``ros__parameters`` mapping) with the identified ``block`` merged in."""
    return _deep_merge(base_ros, block)


def _plain(obj: Any, for_json: bool = False) -> Any:
    """Plain Python types for YAML/JSON; NaN -> null; inf stays a YAML .inf, a JSON "inf" string."""
    if isinstance(obj, dict):
        return {str(k): _plain(v, for_json) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v, for_json) for v in obj]
    if isinstance(obj, np.ndarray):
        return [_plain(v, for_json) for v in obj.tolist()]
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


def _document(block: dict, report: dict, args: argparse.Namespace, vp: Any) -> tuple[dict, str]:
    """The output document and its text; validates the merge with ``--params`` first."""
    if vp is not None:
        from twin_nodes.params import from_ros_dict
        from_ros_dict(merge_into_params(vp.to_ros_dict(), block), path=f"{vp.source} + identified block")
    cmd = _command_line(args)
    as_json = bool(args.out) and Path(args.out).suffix.lower() == ".json"
    doc = {"/**": {"ros__parameters": _plain(block, as_json)},
           "identify": _plain({"command": cmd, **report}, as_json)}
    if as_json:
        text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    else:
        text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110)
    return doc, text


def _command_line(args: argparse.Namespace) -> str:
    """The command line that reproduces this run (rebuilt from the parsed arguments)."""
    parts = ["rotortwin", "identify", args.identify_command]
    for k, v in vars(args).items():
        if k in ("func", "command", "identify_command") or v is None or v is False:
            continue
        if k in ("source", "log"):
            parts.insert(3, shlex.quote(str(v)))
            continue
        flag = "--" + k.replace("_", "-")
        parts.append(flag if v is True else f"{flag} {shlex.quote(str(v))}")
    return " ".join(parts)


def _finish(args: argparse.Namespace, text: str, plot: Callable[[str], None] | None) -> None:
    """Write the plot and the output, each via a temporary file renamed into place."""
    written = []
    try:
        if args.plot and plot is not None:
            tmp = str(args.plot) + ".tmp.png"
            plot(tmp)
            written.append((tmp, args.plot))
        if args.out:
            tmp = str(args.out) + ".tmp"
            Path(tmp).write_text(text, encoding="utf-8")
            written.append((tmp, args.out))
    except Exception:
        for tmp, _ in written:
            with contextlib.suppress(OSError):
                os.remove(tmp)
        raise
    for tmp, final in written:
        os.replace(tmp, final)
    for _, final in written:
        print(f"wrote {final}")


def _table(rows: list[tuple[str, ...]], header: tuple[str, ...] | None = None) -> str:
    allrows = ([header] if header else []) + rows
    widths = [max(len(str(r[i])) for r in allrows) for i in range(len(allrows[0]))]
    lines = []
    for j, r in enumerate(allrows):
        lines.append("  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip())
        if header and j == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _g(v: float, nd: int = 4) -> str:
    return "nan" if v is None or not np.isfinite(v) else f"{v:.{nd}g}"


def _geometry(log: Any, vp: Any, notes: list[str]) -> Any:
    """Rotor geometry: params file, else the log's CA_ROTORn_* (FRD -> FLU), else PX4 quad X."""
    from twin_nodes.identify.regression import RotorGeometry

    if vp is not None:
        return RotorGeometry.from_params(vp)
    n = int(getattr(log, "n_motors", 4))
    p = log.params
    if all(f"CA_ROTOR{i}_PX" in p and f"CA_ROTOR{i}_PY" in p for i in range(n)):
        x = np.array([p[f"CA_ROTOR{i}_PX"] for i in range(n)])
        y_frd = np.array([p[f"CA_ROTOR{i}_PY"] for i in range(n)])
        km = np.array([p.get(f"CA_ROTOR{i}_KM", 0.05) for i in range(n)])
        from twin_nodes import frames
        pos_flu = frames.frd_to_flu(np.column_stack([x, y_frd, np.zeros(n)]))
        notes.append("rotor geometry from the log's CA_ROTORn_PX/PY/KM parameters")
        return RotorGeometry(pos_flu[:, 0], pos_flu[:, 1], np.where(km >= 0, 1.0, -1.0))
    if n != 4:
        raise LogError(log.path, "CA_ROTORn_PX/PY", f"expected rotor positions for {n} rotors (or --params); none in the log")
    notes.append("no CA_ROTORn_* in the log and no --params: PX4 generic quad X geometry assumed (shape only)")
    return RotorGeometry.quad_x(1.0)


def _airborne_mask(log: Any, t: np.ndarray, trim_s: float = 0.0) -> np.ndarray:
    m = np.zeros(t.size, dtype=bool)
    for a, b in log.airborne_intervals():
        m |= (t >= a + trim_s) & (t <= b - trim_s)
    return m


def _height_above_takeoff(log: Any, t: np.ndarray, z_up: np.ndarray) -> np.ndarray:
    """Height above the point each airborne interval started from (NaN outside intervals)."""
    h = np.full(t.size, np.nan)
    for a, b in log.airborne_intervals():
        sel = (t >= a) & (t <= b)
        before = np.flatnonzero((t <= a) & np.isfinite(z_up))
        z0 = z_up[before[-1]] if before.size else (z_up[sel][np.isfinite(z_up[sel])][:1].tolist() or [np.nan])[0]
        h[sel] = z_up[sel] - z0
    return h


# =========================================================================== motor


def _cmd_motor(args: argparse.Namespace) -> int:
    from twin_nodes.identify import step_response as sr

    _check_out_paths(args)
    vp = _load_vp(args)
    src = args.source
    notes: list[str] = []
    datasets: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    if src.lower().endswith(".csv"):
        t, u, rpm = sr.read_step_csv(src)
        datasets.append(("csv", t, u, t, rpm))
        u_label = "command"
    else:
        log = _read_log(src)
        esc = log.get("esc_rpm")
        if esc is None or not np.any(np.isfinite(esc.values) & (esc.values != 0)):
            raise LogError(src, "esc_status.esc[].esc_rpm",
                           "expected ESC RPM telemetry to fit the motor response; this log has none "
                           "(use a bench CSV with columns time_s,command,rpm)")
        mot = log.require("motors")
        for i in range(min(mot.values.shape[1], esc.values.shape[1])):
            ok_u = np.isfinite(mot.values[:, i])
            if np.count_nonzero(ok_u) < 10:
                notes.append(f"motor {i + 1}: fewer than 10 finite commands, skipped")
                continue
            tu, u = mot.t_s[ok_u], mot.values[ok_u, i]
            ok_y = np.isfinite(esc.values[:, i]) & (esc.t_s >= tu[0]) & (esc.t_s <= tu[-1])
            if np.count_nonzero(ok_y) < 10:
                notes.append(f"motor {i + 1}: fewer than 10 RPM samples while commanded, skipped")
                continue
            datasets.append((f"motor{i + 1}", tu, u, esc.t_s[ok_y], esc.values[ok_y, i]))
        if not datasets:
            raise LogError(src, "esc_rpm", "expected at least 10 RPM samples while a motor is commanded")
        u_label = "actuator_motors command [0..1]"
        if "SITL" in str(log.info.get("ver_hw", "")):
            notes.append("SITL log: esc_status RPM is synthetic (PX4 SimulatorMavlink: control x 6000), "
                         "so this checks the pipeline, not a motor")

    results = []
    for name, tu, u, ty, y in datasets:
        try:
            sym = sr.fit_step_response(tu, u, ty, y, asymmetric=False, fit_delay=not args.no_delay,
                                       max_delay_s=args.max_delay)
            asym = sr.fit_step_response(tu, u, ty, y, asymmetric=True, fit_delay=not args.no_delay,
                                        max_delay_s=args.max_delay)
        except ValueError as exc:
            raise LogError(src, name, str(exc)) from None
        disc = sr.discretize_zoh(sym.tau_s, sym.gain, args.rate_hz, delay_s=sym.delay_s,
                                 u_ref=sym.u_ref, y_ref=sym.y_ref)
        results.append((name, tu, u, ty, y, sym, asym, disc))

    tau_up = float(np.median([r[6].tau_up_s for r in results]))
    tau_dn = float(np.median([r[6].tau_down_s for r in results]))
    tau_sym = float(np.median([r[5].tau_s for r in results]))
    if args.symmetric:
        tau_up = tau_dn = tau_sym
    block = {"rotors": {"tau_up_s": tau_up, "tau_down_s": tau_dn}}

    rows = []
    report_fits = {}
    for name, _, _, _, _, sym, asym, disc in results:
        for label, f in (("symmetric", sym), ("up/down", asym)):
            rows.append((name, label, _g(f.tau_up_s), _g(f.tau_down_s), _g(f.gain), _g(f.gain_stderr, 2),
                         f"{f.delay_s * 1e3:.1f}", _g(f.r2, 5), _g(f.rmse)))
        a_up = math.exp(-1.0 / (args.rate_hz * asym.tau_up_s)) if asym.tau_up_s > 0 else 0.0
        a_dn = math.exp(-1.0 / (args.rate_hz * asym.tau_down_s)) if asym.tau_down_s > 0 else 0.0
        report_fits[name] = {
            "symmetric": sym.as_dict(), "asymmetric": asym.as_dict(),
            "gain_rad_s_per_unit": sym.gain * sr.RPM_TO_RAD_S,
            "zoh": {**disc.as_dict(), "equation": "y[k+1] = a*y[k] + b[0]*u[k-n] + b[1]*u[k-n-1] + c",
                    "closed_form_a": math.exp(-1.0 / (args.rate_hz * sym.tau_s)) if sym.tau_s > 0 else 0.0,
                    "a_up": a_up, "a_down": a_dn},
        }
    print(_table(rows, ("data", "model", "tau_up_s", "tau_down_s", "K", "se(K)", "delay_ms", "R2", "rmse")))
    for name, rep in report_fits.items():
        z = rep["zoh"]
        print(f"{name}: ZOH at {args.rate_hz:g} Hz: a = {z['a']:.6f} (exp(-T/tau) = {z['closed_form_a']:.6f}), "
              f"b = [{z['b'][0]:.6g}, {z['b'][1]:.6g}], c = {z['c']:.6g}, n = {z['delay_samples']}")
    print(f"rotors.tau_up_s = {tau_up:.5g} s, rotors.tau_down_s = {tau_dn:.5g} s")
    for n_ in notes:
        print(f"note: {n_}")
    report = {"kind": "motor", "source": src, "fits": report_fits, "notes": notes,
              "zoh_rate_hz": args.rate_hz}
    _, text = _document(block, report, args, vp)

    def plot(path: str) -> None:
        from twin_nodes.identify.plots import plot_step_fit
        name, tu, u, ty, y, sym, asym, _ = results[0]
        plot_step_fit(path, tu, u, ty, y, {"symmetric": sym, "up/down": asym}, u_label=u_label,
                      title=f"{Path(src).name} ({name})")

    _finish(args, text, plot)
    return 0


# =========================================================================== hover


def _cmd_hover(args: argparse.Namespace) -> int:
    from twin_nodes.identify import hover as hv

    _check_out_paths(args)
    vp = _load_vp(args)
    log = _read_log(args.log)
    notes: list[str] = []
    names = ["velocity_enu", "throttle", "position_enu"]
    opt = [n for n in ("attitude_q", "motors", "esc_rpm", "hover_thrust") if log.get(n) is not None]
    for n in names:
        log.require(n)
    t, v = log.resample(names + [n for n in opt if n != "hover_thrust"], 10.0)
    hte = log.get("hover_thrust").at(t) if "hover_thrust" in opt else None
    air = _airborne_mask(log, t)
    if not np.any(air):
        raise LogError(args.log, "landed", "expected an airborne stretch (land detector), found none")
    motors = v.get("motors")
    rpm = v.get("esc_rpm")
    height = _height_above_takeoff(log, t, v["position_enu"][:, 2])
    segs = hv.detect_hover_segments(
        t, v["velocity_enu"], v["throttle"][:, 0], airborne=air, attitude_q=v.get("attitude_q"),
        height_m=height, min_height_m=args.min_height,
        motors=motors, rpm=rpm, min_duration_s=args.min_duration, max_vz_m_s=args.max_vz,
        max_vxy_m_s=args.max_vxy, max_az_m_s2=args.max_az)
    if not segs:
        raise LogError(args.log, "velocity_enu",
                       f"expected a steady hover of >= {args.min_duration:g} s (|vz| <= {args.max_vz:g} m/s, "
                       f"|vxy| <= {args.max_vxy:g} m/s, |az| <= {args.max_az:g} m/s^2), found none")
    summ = hv.summarize_hover(segs)
    mass = args.mass_kg if args.mass_kg is not None else (vp.mass_kg if vp is not None else None)
    grav = vp.gravity_m_s2 if vp is not None else hv.GRAVITY_DEFAULT
    block: dict = {}
    report: dict = {"kind": "hover", "source": args.log, "summary": summ.as_dict(),
                    "segments": [s.as_dict() for s in segs], "notes": notes,
                    "px4_MPC_THR_HOVER": log.params.get("MPC_THR_HOVER")}
    motor_means = None
    if motors is not None and all(s.motors_mean is not None for s in segs):
        w = np.array([s.duration_s for s in segs])
        motor_means = np.average(np.array([s.motors_mean for s in segs]), axis=0, weights=w)
        report["motor_command_mean"] = motor_means
        report["motor_command_mean_all"] = float(np.mean(motor_means))
    if hte is not None:
        vals = [np.nanmean(hte[(t >= s.t_start_s) & (t <= s.t_end_s)]) for s in segs]
        report["px4_hover_thrust_estimate_in_segments"] = [float(x) for x in vals]

    rows = [(f"{s.t_start_s:.1f}-{s.t_end_s:.1f}", f"{s.duration_s:.1f}", f"{s.throttle_mean:.4f}",
             f"{s.throttle_std:.4f}",
             "-" if s.motors_mean is None else " ".join(f"{x:.3f}" for x in s.motors_mean),
             "-" if s.rpm_mean is None else " ".join(f"{x:.0f}" for x in s.rpm_mean))
            for s in segs]
    print(_table(rows, ("segment_s", "dur_s", "throttle", "std", "motors_mean", "rpm_mean")))
    print(f"hover throttle {summ.throttle_mean:.4f} (between segments {summ.between_std:.4f}, "
          f"within {summ.within_std:.4f}) over {summ.n_segments} segment(s), {summ.total_s:.1f} s; "
          f"PX4 MPC_THR_HOVER {log.params.get('MPC_THR_HOVER')}")

    has_rpm = rpm is not None and all(s.rpm_mean is not None and np.all(s.rpm_mean > 0) for s in segs)
    if has_rpm:
        if mass is None:
            raise ParamsError("--mass-kg/--params", "vehicle.mass_kg",
                              "the log has rotor RPM; kt = m g / sum(w^2) needs the mass")
        kts = hv.kt_per_segment(segs, mass, grav)
        w = np.array([s.duration_s for s in segs])
        kt = float(np.average(kts, weights=w))
        block = {"rotors": {"kt_n_s2_rad2": kt}}
        report["kt_n_s2_rad2"] = {"value": kt, "per_segment": kts, "spread": float(np.std(kts)),
                                  "mass_kg": mass, "gravity_m_s2": grav}
        print(f"kt = m g / sum(w_i^2) = {kt:.5g} N/(rad/s)^2 (per segment {', '.join(_g(k) for k in kts)})")
        if "SITL" in str(log.info.get("ver_hw", "")):
            notes.append("SITL esc_status RPM is synthetic (control x 6000), so this kt is not physical")
    elif vp is not None:
        u_h = float(np.mean(motor_means)) if motor_means is not None else summ.throttle_mean
        derived = hv.params_from_hover_command(vp, u_h)
        block = {"rotors": derived}
        report["derived_from_hover_command"] = {"hover_command": u_h, **derived,
                                                "thrust_model": vp.rotors.thrust_model}
        k, val = next(iter(derived.items()))
        print(f"no RPM in the log: hover command {u_h:.4f} with {vp.source}'s {vp.rotors.thrust_model} "
              f"map gives rotors.{k} = {val:.5g}")
    else:
        notes.append("no RPM and no --params: only the hover throttle is reported (no parameter-file key)")
    for n_ in notes:
        print(f"note: {n_}")
    _, text = _document(block, report, args, vp)

    def plot(path: str) -> None:
        from twin_nodes.identify.plots import plot_hover
        plot_hover(path, t, v["throttle"][:, 0], segs, v["velocity_enu"], hte, title=Path(args.log).name)

    _finish(args, text, plot)
    return 0


# =========================================================================== delay

DELAY_PAIRS = ("thrust", "motors", "torque_roll", "torque_pitch", "torque_yaw",
               "motor_roll", "motor_pitch", "motor_yaw", "climb")


def _angular_accel(log: Any, source: str = "rates") -> tuple[np.ndarray, np.ndarray, str]:
    """Angular acceleration (t, (n, 3) FLU, description).

    ``"rates"`` (default): central differences of the logged body rates at their
    own time stamps; any smoothing is left to the caller, which applies the same
    low-pass to both sides of a regression.  ``"px4"``: PX4's own
    ``xyz_derivative``; on these logs it is a 50 Hz *sample* of a ~1 kHz
    differentiated signal and aliases badly (R2 0.1 against 0.6 on the SIH log).
    """
    aa = log.get("angular_accel_flu")
    if source == "px4":
        if aa is None:
            raise LogError(log.path, "vehicle_angular_velocity.xyz_derivative",
                           "expected PX4's angular acceleration (PX4 >= v1.12); use --accel-source rates")
        return aa.t_s, aa.values, "angular_accel_flu (PX4 xyz_derivative)"
    br = log.require("body_rates_flu")
    ok = np.all(np.isfinite(br.values), axis=1)
    t = br.t_s[ok]
    return t, np.gradient(br.values[ok], t, axis=0), "d/dt body_rates_flu (central differences)"


def _delay_inputs(log: Any, geometry: Any) -> dict[str, tuple]:
    out: dict[str, tuple] = {}
    thr, sf, mot = log.get("throttle"), log.get("specific_force_flu"), log.get("motors")
    if thr is not None and sf is not None:
        out["thrust"] = ("throttle -> specific force z", thr.t_s, thr.values[:, 0], sf.t_s, sf.values[:, 2],
                         (-0.1, 0.3))
    if mot is not None and sf is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all motors NaN while disarmed
            mean = np.nanmean(mot.values, axis=1)
        out["motors"] = ("mean motor command -> specific force z", mot.t_s, mean, sf.t_s, sf.values[:, 2],
                         (-0.1, 0.3))
    ta, aa, src = _angular_accel(log) if log.get("body_rates_flu") is not None else (None, None, "")
    tq = log.get("torque_setpoint_flu")
    if ta is not None:
        for k, ax in enumerate(("roll", "pitch", "yaw")):
            if tq is not None:
                out[f"torque_{ax}"] = (f"torque setpoint {ax} -> {src}", tq.t_s, tq.values[:, k], ta, aa[:, k],
                                       (-0.1, 0.3))
            if mot is not None and geometry is not None:
                u = np.where(np.isfinite(mot.values), mot.values, np.nan)
                l = geometry.arm_length_m
                w = {"roll": geometry.y_flu_m / l, "pitch": -geometry.x_flu_m / l,
                     "yaw": -geometry.direction}[ax]
                out[f"motor_{ax}"] = (f"motor differential {ax} -> {src}", mot.t_s, u @ w, ta, aa[:, k],
                                      (-0.1, 0.3))
    sv, vel = log.get("setpoint_velocity_enu"), log.get("velocity_enu")
    if sv is not None and vel is not None:
        out["climb"] = ("velocity setpoint up -> velocity up", sv.t_s, sv.values[:, 2], vel.t_s, vel.values[:, 2],
                        (-0.5, 2.0))
    return out


def _cmd_delay(args: argparse.Namespace) -> int:
    from twin_nodes.identify.delay import estimate_delay

    _check_out_paths(args)
    vp = _load_vp(args)
    log = _read_log(args.log)
    notes: list[str] = []
    wanted = DELAY_PAIRS if not args.pairs else tuple(p.strip() for p in args.pairs.split(",") if p.strip())
    unknown = [p for p in wanted if p not in DELAY_PAIRS]
    if unknown:
        raise ParamsError("--pairs", unknown[0], f"unknown pair; expected some of {', '.join(DELAY_PAIRS)}")
    try:
        geometry = _geometry(log, vp, notes)
    except LogError as exc:
        geometry = None
        notes.append(f"no rotor geometry ({exc.expected}): motor_* pairs skipped")
    inputs = _delay_inputs(log, geometry)
    iv = log.airborne_intervals()
    if not iv:
        raise LogError(args.log, "landed", "expected an airborne stretch (land detector), found none")
    a, b = max(iv, key=lambda x: x[1] - x[0])
    a, b = a + 1.0, b - 1.0
    ests = []
    for name in wanted:
        if name not in inputs:
            if args.pairs:
                raise LogError(args.log, name, "expected the series this pair needs; not in this log")
            continue
        label, tc, c, tr, r, (lo, hi) = inputs[name]
        sc = (tc >= a) & (tc <= b) & np.isfinite(c)
        sr_ = (tr >= a) & (tr <= b) & np.isfinite(r)
        try:
            e = estimate_delay(tc[sc], c[sc], tr[sr_], r[sr_], max_delay_s=hi, min_delay_s=lo, mode=args.mode,
                               highpass_s=None if name == "climb" or not args.highpass_s else args.highpass_s,
                               n_boot=args.boot, label=f"{name}: {label}")
        except ValueError as exc:
            notes.append(f"{name}: {exc}")
            continue
        ests.append((name, e))
    if not ests:
        raise LogError(args.log, "delay pairs", f"expected at least one usable command/response pair; {'; '.join(notes)}")
    rows = [(n, f"{e.delay_s * 1e3:.1f}", f"[{e.ci_low_s * 1e3:.1f}, {e.ci_high_s * 1e3:.1f}]",
             f"{e.peak_corr:+.3f}", e.label.split(": ", 1)[1]) for n, e in ests]
    print(_table(rows, ("pair", "delay_ms", "95% CI ms", "peak_r", "command -> response")))
    for n_ in notes:
        print(f"note: {n_}")
    report = {"kind": "delay", "source": args.log, "window_s": [a, b], "mode": args.mode,
              "delays": {n: e.as_dict() for n, e in ests}, "notes": notes}
    _, text = _document({}, report, args, vp)

    def plot(path: str) -> None:
        from twin_nodes.identify.plots import plot_delays
        plot_delays(path, [e for _, e in ests], title=Path(args.log).name)

    _finish(args, text, plot)
    return 0


# =========================================================================== regress


def _cmd_regress(args: argparse.Namespace) -> int:
    from twin_nodes.identify import regression as rg

    _check_out_paths(args)
    vp = _load_vp(args)
    log = _read_log(args.log)
    notes: list[str] = []
    geometry = _geometry(log, vp, notes)
    mot = log.require("motors")
    if mot.values.shape[1] != geometry.count:
        raise LogError(args.log, "motors", f"expected {geometry.count} motors (geometry), got {mot.values.shape[1]}")
    # Rotor states at the log's own motor sample times (ZOH + exact lag), then resampled.
    if vp is not None:
        r = vp.rotors
        states = rg.rotor_states_from_commands(mot.t_s, mot.values, tau_up_s=r.tau_up_s, tau_down_s=r.tau_down_s,
                                               reference=r.reference_from_command)
        model, fac = r.thrust_model, r.thr_mdl_fac
        notes.append(f"rotor states from {vp.source}: {model}, tau_up {r.tau_up_s:g} s, tau_down {r.tau_down_s:g} s")
    else:
        states = rg.rotor_states_from_commands(mot.t_s, mot.values, tau_up_s=args.tau_s)
        model, fac = "command", 0.0
        notes.append(f"no --params: thrust taken proportional to the lagged motor command (tau {args.tau_s:g} s); "
                     "kT is thrust per unit command")
    tt_native = rg.thrust_regressor(states, model, fac)

    names = ["specific_force_flu", "velocity_enu", "attitude_q", "body_rates_flu"]
    for n in names:
        log.require(n)
    t, v = log.resample(names, args.rate_hz)
    tt = np.column_stack([np.interp(t, mot.t_s, tt_native[:, j], left=np.nan, right=np.nan)
                          for j in range(tt_native.shape[1])])
    ta, aa, aa_src = _angular_accel(log, args.accel_source)
    acc = np.column_stack([np.interp(t, ta, aa[:, k], left=np.nan, right=np.nan) for k in range(3)])
    notes.append(f"angular acceleration: {aa_src}")
    vb = rg.world_to_body(v["attitude_q"], v["velocity_enu"])
    motor_rate = (len(mot) - 1) / (mot.t_s[-1] - mot.t_s[0])
    lp = args.lowpass_hz if args.lowpass_hz is not None else min(8.0, 0.4 * motor_rate)
    notes.append(f"zero-phase low-pass {lp:g} Hz on both sides (motors logged at {motor_rate:.1f} Hz)")

    # Airborne stretches only (ground reaction is not in the model), each filtered on its own.
    segs = []
    for a, b in log.airborne_intervals():
        sel = np.flatnonzero((t >= a + args.trim_s) & (t <= b - args.trim_s))
        if sel.size < max(20, int(2 * args.rate_hz)):
            continue
        block_ = np.column_stack([v["specific_force_flu"][sel], vb[sel], v["body_rates_flu"][sel], acc[sel], tt[sel]])
        ok = np.all(np.isfinite(block_), axis=1)
        # keep the longest finite run inside the stretch (filters need contiguous data)
        runs = np.split(np.arange(sel.size), np.flatnonzero(np.diff(ok.astype(int)) != 0) + 1)
        runs = [rr for rr in runs if ok[rr[0]]]
        if not runs:
            continue
        rr = max(runs, key=len)
        if rr.size < max(20, int(2 * args.rate_hz)):
            continue
        segs.append((t[sel[rr]], rg.lowpass(block_[rr], args.rate_hz, lp)))
    if not segs:
        raise LogError(args.log, "landed", f"expected airborne data longer than 2 x {args.trim_s:g} s trim + 2 s")
    ts = np.concatenate([s[0] for s in segs])
    data = np.concatenate([s[1] for s in segs])
    f, vbb, w, wd, T = data[:, 0:3], data[:, 3:6], data[:, 6:9], data[:, 9:12], data[:, 12:]
    trans = rg.translational_regression(f, T, vbb, intercept=args.intercept, rcond=args.rcond)
    rot = rg.rotational_regression(wd, w, T, geometry, intercept=args.intercept, rcond=args.rcond)

    rows = []
    for eq, fits in (("trans", trans), ("rot", rot)):
        for ax, fit in fits.items():
            for i, nm in enumerate(fit.names):
                rows.append((f"{eq} {ax}", nm, _g(fit.coef[i]), _g(fit.stderr[i], 2), f"{fit.t_values[i]:.1f}",
                             "yes" if fit.identifiable[i] else "NO", _g(fit.r2, 3), _g(fit.condition_number, 3)))
    print(_table(rows, ("equation", "coefficient", "value", "stderr", "t", "ident.", "R2", "cond")))
    for fits in (trans, rot):
        for ax, fit in fits.items():
            for c in fit.combinations:
                print(f"{ax}: only the combination {c.text()} = {_g(c.value)} +- {_g(c.stderr, 2)} is identifiable")

    # Which coefficients the data determined (identifiable, |t| >= 3), and what that says about physics.
    identified = [nm for fits in (trans, rot) for fit in fits.values()
                  for nm, ok_, tv in zip(fit.names, fit.identifiable, fit.t_values)
                  if ok_ and abs(tv) >= 3.0 and not nm.startswith("bias")]
    nominal = None
    known: tuple[str, ...] = ()
    if vp is not None:
        I = vp.inertia
        nominal = {"m": vp.mass_kg, "l": geometry.arm_length_m, "km": vp.rotors.km_m,
                   "Ixx": I[0, 0], "Iyy": I[1, 1], "Izz": I[2, 2],
                   "kT": vp.rotors.kt_n_s2_rad2 if model == "omega_squared" else vp.rotors.thrust_max_n}
        known = ("m", "l", "km")
    struct_free = rg.structural_identifiability(identified, nominal)
    struct_known = rg.structural_identifiability(identified, nominal, known=known) if known else None
    print("identified combinations (|t| >= 3): " + ", ".join(identified))
    for line in struct_free.describe():
        print(f"not separately identifiable: {line}")
    if struct_known is not None:
        print(f"with m, l, km from {vp.source}: separately identifiable: "
              + (", ".join(struct_known.determined) or "none")
              + ("" if not struct_known.null_directions else
                 "; still tied: " + "; ".join(", ".join(d) for d in struct_known.null_directions)))

    block: dict = {}
    implied: dict = {}
    if vp is not None:
        l = geometry.arm_length_m

        def good(fit: Any, nm: str) -> bool:
            # Identifiable, positive and within 5 % (1 sigma); a low R2 with white
            # sensor noise still gives an unbiased, precise coefficient.
            i = fit.names.index(nm)
            return bool(fit.identifiable[i] and fit.coef[i] > 0 and abs(fit.t_values[i]) >= 20.0)

        tz = trans["z"]
        if "kT/m" in tz.names and good(tz, "kT/m"):
            kT = tz["kT/m"] * vp.mass_kg
            implied["kT"] = kT
            key = "kt_n_s2_rad2" if model == "omega_squared" else "thrust_max_n"
            block.setdefault("rotors", {})[key] = kT
            for ax, nm, ikey in (("roll", "kT*l/Ixx", "ixx_kg_m2"), ("pitch", "kT*l/Iyy", "iyy_kg_m2")):
                if good(rot[ax], nm):
                    implied[ikey] = kT * l / rot[ax][nm]
            if good(rot["yaw"], "km*kT/Izz") and vp.rotors.km_m > 0:
                implied["izz_kg_m2"] = vp.rotors.km_m * kT / rot["yaw"]["km*kT/Izz"]
            inert = {k: implied[k] for k in ("ixx_kg_m2", "iyy_kg_m2", "izz_kg_m2") if k in implied}
            if inert:
                block["vehicle"] = inert
        else:
            notes.append("kT/m not well determined (relative stderr > 5 % or <= 0): no parameter-file keys written")
        for k, val in implied.items():
            print(f"implied (m, l, km from params): {k} = {_g(val)}")
        if block:
            from twin_nodes.params import from_ros_dict
            try:
                from_ros_dict(merge_into_params(vp.to_ros_dict(), block), path="merged")
            except ParamsError as exc:
                notes.append(f"implied values rejected by the params schema ({exc}); not written")
                block = {}
    for n_ in notes:
        print(f"note: {n_}")
    report = {"kind": "regress", "source": args.log, "n_samples": int(ts.size), "rate_hz": args.rate_hz,
              "lowpass_hz": lp, "thrust_model": model,
              "translational": {ax: f_.as_dict() for ax, f_ in trans.items()},
              "rotational": {ax: f_.as_dict() for ax, f_ in rot.items()},
              "structural": struct_free.as_dict(),
              "structural_with_m_l_km_known": struct_known.as_dict() if struct_known else None,
              "implied": implied, "notes": notes}
    _, text = _document(block, report, args, vp)

    def plot(path: str) -> None:
        from twin_nodes.identify.plots import plot_regression
        cols_t = rg.translational_columns(T, vbb, intercept=args.intercept)
        cols_r = rg.rotational_columns(w, T, geometry, intercept=args.intercept)
        panels = []
        for ax, k in (("x", 0), ("y", 1), ("z", 2)):
            if ax in trans:
                panels.append((f"f_{ax} [m/s2]", f[:, k], trans[ax].predict(cols_t[ax][0]), trans[ax].r2))
        for ax, k in (("roll", 0), ("pitch", 1), ("yaw", 2)):
            panels.append((f"dw_{ax} [rad/s2]", wd[:, k], rot[ax].predict(cols_r[ax][0]), rot[ax].r2))
        plot_regression(path, ts, panels, title=Path(args.log).name)

    _finish(args, text, plot)
    return 0


# =========================================================================== noise


def _cmd_noise(args: argparse.Namespace) -> int:
    from twin_nodes.identify import noise as nz

    _check_out_paths(args)
    vp = _load_vp(args)
    log = _read_log(args.log)
    notes: list[str] = []
    gy = log.require("gyro_flu")
    sf = log.require("specific_force_flu")
    if len(gy) != len(sf):
        raise LogError(args.log, "sensor_combined", f"expected as many accel as gyro samples, got {len(sf)} and {len(gy)}")
    t = gy.t_s
    landed = log.get("landed")
    armed = log.get("armed")
    if landed is None or armed is None:
        raise LogError(args.log, "vehicle_land_detected/vehicle_status",
                       "expected land detector and arming state to find the ground segment")
    is_landed = landed.at(t)[:, 0] > 0.5
    is_armed = armed.at(t)[:, 0] > 0.5
    g_all, a_all = gy.values, sf.values
    runs = nz.stationary_runs(t, g_all, a_all, min_duration_s=args.min_duration,
                              gyro_std_max=args.gyro_std_max, accel_std_max=args.accel_std_max)
    cand = []
    for want_armed in ((False, True) if args.allow_armed else (False,)):
        ok = is_landed & (is_armed == want_armed)
        for a, b in runs:
            sub = np.flatnonzero(ok[a:b]) + a
            if sub.size == 0:
                continue
            pieces = np.split(sub, np.flatnonzero(np.diff(sub) != 1) + 1)
            for pc in pieces:
                if t[pc[-1]] - t[pc[0]] >= args.min_duration:
                    cand.append((want_armed, pc))
        if cand:
            break
    if not cand:
        what = "landed (disarmed, or armed with --allow-armed)" if args.allow_armed else \
            "landed and disarmed (pre-arm ground segment)"
        raise LogError(args.log, "sensor_combined",
                       f"expected >= {args.min_duration:g} s stationary (1 s std of gyro <= {args.gyro_std_max:g} "
                       f"rad/s, of |accel| <= {args.accel_std_max:g} m/s^2), {what}; none found"
                       + ("" if args.allow_armed else " (logging may start at arming: try --allow-armed)"))
    used_armed, idx = max(cand, key=lambda c: c[1].size)
    if used_armed:
        notes.append("no disarmed ground segment: used landed+armed samples, so motor vibration is included")
    tt = t[idx]
    dt = np.diff(tt)
    rate = 1.0 / float(np.mean(dt))
    jitter = float(np.std(dt) / np.mean(dt))
    if jitter > 0.05:
        notes.append(f"sample interval jitter {jitter:.1%}: Allan deviation computed on sample index at the mean rate")
    notes.append("PX4 sensor_combined is low-pass filtered (IMU_GYRO_CUTOFF "
                 f"{log.params.get('IMU_GYRO_CUTOFF')} Hz) and decimated: white-noise std is of the filtered "
                 "signal; random walk from the Allan -1/2 slope is not affected by the filter")
    res = nz.imu_noise(g_all[idx], a_all[idx], rate,
                       gravity_m_s2=vp.gravity_m_s2 if vp is not None else nz.GRAVITY_DEFAULT,
                       accel_reference=args.accel_reference)
    block = {"sensors": nz.sensors_block(res)}
    d = res.as_dict()
    rows = []
    for key, unit in (("gyro_bias_rad_s", "rad/s"), ("gyro_noise_rad_s", "rad/s"),
                      ("gyro_arw_rad_s_sqrt_hz", "rad/s/sqrt(Hz)"), ("gyro_bias_instability_rad_s", "rad/s"),
                      ("accel_bias_m_s2", "m/s^2"), ("accel_noise_m_s2", "m/s^2"),
                      ("accel_vrw_m_s2_sqrt_hz", "m/s^2/sqrt(Hz)"), ("accel_bias_instability_m_s2", "m/s^2")):
        rows.append((key, *(f"{x:.3e}" for x in d[key]), unit))
    print(f"stationary segment {tt[0]:.2f}-{tt[-1]:.2f} s ({tt[-1] - tt[0]:.1f} s, {idx.size} samples, "
          f"{rate:.1f} Hz, {'armed' if used_armed else 'disarmed'}, landed)")
    print(_table(rows, ("quantity", "x", "y", "z", "unit")))
    unb = [a for a, ok_ in zip("xyz", res.gyro_allan.bias_instability_bounded) if not ok_]
    if unb:
        notes.append(f"gyro Allan deviation still falling at the longest tau on axis {','.join(unb)}: "
                     "bias instability there is an upper bound")
    unb = [a for a, ok_ in zip("xyz", res.accel_allan.bias_instability_bounded) if not ok_]
    if unb:
        notes.append(f"accel Allan deviation still falling at the longest tau on axis {','.join(unb)}: "
                     "bias instability there is an upper bound")
    for n_ in notes:
        print(f"note: {n_}")
    report = {"kind": "noise", "source": args.log, "segment_s": [float(tt[0]), float(tt[-1])],
              "armed": bool(used_armed), "imu": d, "notes": notes}
    _, text = _document(block, report, args, vp)

    def plot(path: str) -> None:
        from twin_nodes.identify.plots import plot_allan
        plot_allan(path, res.gyro_allan, res.accel_allan,
                   title=f"{Path(args.log).name}: {tt[0]:.1f}-{tt[-1]:.1f} s")

    _finish(args, text, plot)
    return 0
