"""``rotortwin identify``: the second reference's parameter identification from data.

::

    rotortwin identify motor   STEPS.csv|LOG.ulg [--rate-hz 30] [--no-delay] [--symmetric]
    rotortwin identify hover   LOG.ulg [--mass-kg M] [--min-duration 3]
    rotortwin identify delay   LOG.ulg [--pairs thrust,torque_roll,...]
    rotortwin identify regress LOG.ulg [--rate-hz 50] [--lowpass-hz 2.5] [--tau-s 0.05]
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
``twin_nodes.vehicle.params.from_ros_dict`` before anything is written.

Motor CSV format: a header row with columns ``time_s,command,rpm`` (see
:mod:`twin_nodes.identify.step_response`).

Bad input raises :class:`~twin_nodes.base.errors.LogError` / ``ParamsError`` with a
one-line message; every result is computed and checked before any file is
written, so a failure leaves nothing behind.
"""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path
from typing import Any, Callable

import yaml

from twin_nodes.base.errors import ParamsError
from twin_nodes.base.outputs import shown
from twin_nodes.cli.paths import declare
from twin_nodes.cli.options import MASS_KG, RATE_HZ, SECONDS, finite_float, integer, nonneg_float, positive_float

OUT_SUFFIXES = (".yaml", ".yml", ".json")
#: the ``--pairs`` choices: every pair :func:`twin_nodes.identify.from_log.delay_inputs` can build
DELAY_PAIRS = ("thrust", "motors", "torque_roll", "torque_pitch", "torque_yaw",
               "motor_roll", "motor_pitch", "motor_yaw", "climb")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("identify", help="identify motor lag, hover thrust, delays, model coefficients, IMU noise",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="identify_command", metavar="WHAT")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    m = sub.add_parser("motor", help="first-order motor model K/(tau s+1) (+delay) from command/rpm steps")
    declare(m).input("source", help="CSV with time_s,command,rpm columns, or a ULog with esc_status RPM")
    m.add_argument("--rate-hz", type=RATE_HZ, default=30.0,
                   help="rate of the ZOH difference equation (reference: 30 Hz PWM logging)")
    m.add_argument("--no-delay", action="store_true", help="do not fit a pure delay")
    m.add_argument("--max-delay", type=positive_float(10.0, "s"), default=0.5, help="largest delay to consider [s]")
    m.add_argument("--symmetric", action="store_true",
                   help="write the symmetric tau as both tau_up_s and tau_down_s")
    _common(m)
    m.set_defaults(func=_handler(_motor))

    h = sub.add_parser("hover", help="hover throttle from steady-hover segments; kt = m g / (N w^2) with RPM")
    declare(h).input("log", help="ULog")
    h.add_argument("--mass-kg", type=MASS_KG, help="vehicle mass (else from --params)")
    h.add_argument("--min-duration", type=SECONDS, default=3.0, help="shortest hover segment [s]")
    h.add_argument("--max-vz", type=positive_float(100.0, "m/s"), default=0.3, help="largest vertical speed in hover [m/s]")
    h.add_argument("--max-vxy", type=positive_float(100.0, "m/s"), default=0.5, help="largest horizontal speed in hover [m/s]")
    h.add_argument("--max-az", type=positive_float(100.0, "m/s^2"), default=0.5, help="largest vertical acceleration [m/s^2]")
    h.add_argument("--min-height", type=finite_float(-1000.0, 10000.0, unit="m"), default=1.0, help="smallest height above the take-off point [m]")
    _common(h)
    h.set_defaults(func=_handler(_hover))

    d = sub.add_parser("delay", help="command -> response delays by cross-correlation")
    declare(d).input("log", help="ULog")
    d.add_argument("--pairs", help=f"comma-separated subset of: {', '.join(DELAY_PAIRS)} (default: all available)")
    d.add_argument("--mode", choices=("level", "diff"), default="level",
                   help="correlate detrended levels or first differences")
    d.add_argument("--highpass-s", type=nonneg_float(3600.0, "s"), default=1.0,
                   help="remove a moving average this long from both series first (0: off; not for 'climb')")
    d.add_argument("--boot", type=integer(0, 100000), default=300, help="bootstrap replicates for the 95 %% interval")
    _common(d)
    d.set_defaults(func=_handler(_delay))

    r = sub.add_parser("regress", help="equation-error least squares of translational and rotational dynamics")
    declare(r).input("log", help="ULog")
    r.add_argument("--rate-hz", type=RATE_HZ, default=50.0, help="resampling rate [Hz]")
    r.add_argument("--lowpass-hz", type=RATE_HZ,
                   help="zero-phase low-pass applied to both sides (default: 2.5 Hz, at most 0.4 x the motor log rate)")
    r.add_argument("--tau-s", type=positive_float(10.0, "s"), default=0.05,
                   help="motor time constant when no --params is given [s]")
    r.add_argument("--trim-s", type=nonneg_float(3600.0, "s"), default=2.0,
                   help="drop this much after take-off and before touchdown (ground contact) [s]")
    r.add_argument("--accel-source", choices=("rates", "px4"), default="rates",
                   help="angular acceleration from differentiated body rates or PX4's xyz_derivative")
    r.add_argument("--intercept", action="store_true", help="add a constant term to every equation")
    r.add_argument("--rcond", type=finite_float(0.0, 1.0, lo_open=True, hi_open=True), default=1e-3,
                   help="relative singular-value threshold below which a direction counts as unidentifiable")
    _common(r)
    r.set_defaults(func=_handler(_regress))

    n = sub.add_parser("noise", help="IMU bias, white noise and Allan deviation from the pre-arm ground segment")
    declare(n).input("log", help="ULog")
    n.add_argument("--allow-armed", action="store_true",
                   help="if there is no landed+disarmed stretch, use landed+armed (motor vibration included)")
    n.add_argument("--min-duration", type=SECONDS, default=3.0, help="shortest stationary stretch [s]")
    n.add_argument("--gyro-std-max", type=positive_float(100.0, "rad/s"), default=0.02,
                   help="stationary: largest 1 s moving std of each gyro axis [rad/s]")
    n.add_argument("--accel-std-max", type=positive_float(1000.0, "m/s^2"), default=0.15,
                   help="stationary: largest 1 s moving std of the accelerometer magnitude [m/s^2]")
    n.add_argument("--accel-reference", choices=("mean_direction", "level"), default="mean_direction",
                   help="what the accelerometer should read at rest (see twin_nodes.identify.noise)")
    _common(n)
    n.set_defaults(func=_handler(_noise))


def _common(p: argparse.ArgumentParser) -> None:
    io = declare(p)
    io.input("--params", help="vehicle params YAML (mass, rotor geometry, command map)")
    io.output("--out", help="write the result here (.yaml/.yml or .json)")
    io.output("--plot", help="write a PNG figure here")


def _handler(compute: Callable[[argparse.Namespace, Any], Any]) -> Callable[[argparse.Namespace], int]:
    """Check the output paths, load ``--params``, ``compute``, print its summary and notes, write the files."""
    def handle(args: argparse.Namespace) -> int:
        _check_out_paths(args)
        from twin_nodes.vehicle.params import load_params
        vp = load_params(args.params) if args.params else None
        res = compute(args, vp)
        print("\n".join(res.summary_lines() + [f"note: {n}" for n in res.notes]))  # never empty
        _finish(args, _document(res.block, res.report, args, vp), res.plot)
        return 0
    return handle


def _read_log(path: str) -> Any:
    from twin_nodes.logs.ulog_io import read_ulog
    return read_ulog(path)


def _motor(args: argparse.Namespace, vp: Any) -> Any:
    from twin_nodes.identify.from_log import identify_motor
    log = None if args.source.lower().endswith(".csv") else _read_log(args.source)
    return identify_motor(args.source, log, rate_hz=args.rate_hz, fit_delay=not args.no_delay,
                          max_delay_s=args.max_delay, symmetric=args.symmetric)


def _hover(args: argparse.Namespace, vp: Any) -> Any:
    from twin_nodes.identify.from_log import hover_flight, hover_parameters
    flight = hover_flight(_read_log(args.log), source=args.log, min_duration_s=args.min_duration,
                          max_vz_m_s=args.max_vz, max_vxy_m_s=args.max_vxy, max_az_m_s2=args.max_az,
                          min_height_m=args.min_height)
    print("\n".join(flight.summary_lines()))  # before hover_parameters, which may need a mass not given
    return hover_parameters(flight, vp, args.mass_kg)


def _delay(args: argparse.Namespace, vp: Any) -> Any:
    from twin_nodes.identify.from_log import identify_delays
    log = _read_log(args.log)
    pairs = [p.strip() for p in args.pairs.split(",") if p.strip()] if args.pairs else None
    if unknown := [p for p in pairs or () if p not in DELAY_PAIRS]:
        raise ParamsError("--pairs", unknown[0], f"unknown pair; expected some of {', '.join(DELAY_PAIRS)}")
    return identify_delays(log, vp, source=args.log, pairs=pairs, mode=args.mode, highpass_s=args.highpass_s,
                           n_boot=args.boot)


def _regress(args: argparse.Namespace, vp: Any) -> Any:
    from twin_nodes.identify.from_log import identify_regression
    return identify_regression(_read_log(args.log), vp, source=args.log, rate_hz=args.rate_hz,
                               lowpass_hz=args.lowpass_hz, tau_s=args.tau_s, trim_s=args.trim_s,
                               accel_source=args.accel_source, intercept=args.intercept, rcond=args.rcond)


def _noise(args: argparse.Namespace, vp: Any) -> Any:
    from twin_nodes.identify.from_log import identify_noise
    return identify_noise(_read_log(args.log), vp, source=args.log, allow_armed=args.allow_armed,
                          min_duration_s=args.min_duration, gyro_std_max=args.gyro_std_max,
                          accel_std_max=args.accel_std_max, accel_reference=args.accel_reference)


def _check_out_paths(args: argparse.Namespace) -> None:
    if args.out:
        suf = Path(args.out).suffix.lower()
        if suf not in OUT_SUFFIXES:
            raise ParamsError(args.out, "--out", f"expected a file name ending in {', '.join(OUT_SUFFIXES)}, got {suf or 'no suffix'!r}")
    if args.plot:
        if Path(args.plot).suffix.lower() != ".png":
            raise ParamsError(args.plot, "--plot", "expected a .png file name")


def _document(block: dict, report: dict, args: argparse.Namespace, vp: Any) -> str:
    """The output document's text; validates the merge with ``--params`` first."""
    from twin_nodes.identify.results import check_merged, plain
    if vp is not None:
        check_merged(vp, block, f"{vp.source} + identified block")
    as_json = bool(args.out) and Path(args.out).suffix.lower() == ".json"
    doc = {"/**": {"ros__parameters": plain(block, as_json)},
           "identify": plain({"command": _command_line(args), **report}, as_json)}
    if as_json:
        return json.dumps(doc, indent=2, allow_nan=False) + "\n"
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110)


def _command_line(args: argparse.Namespace) -> str:
    """The command line that reproduces this run (rebuilt from the parsed arguments)."""
    parts = ["rotortwin", "identify", args.identify_command]
    for k, v in vars(args).items():
        if k in ("func", "command", "identify_command") or k.startswith("_") or v is None or v is False:
            continue
        if k in ("source", "log"):
            parts.insert(3, shlex.quote(str(v)))
            continue
        flag = "--" + k.replace("_", "-")
        parts.append(flag if v is True else f"{flag} {shlex.quote(shown(v))}")
    return " ".join(parts)


def _finish(args: argparse.Namespace, text: str, plot: Callable[[str], None]) -> None:
    """Write the plot and the output (staged by the CLI's guard: renamed into place only when the
    command succeeded, so a failure here leaves nothing)."""
    if args.plot:
        plot(args.plot)
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
