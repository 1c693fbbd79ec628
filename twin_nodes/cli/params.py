"""``rotortwin params``: derive, check and export vehicle parameter files.

::

    rotortwin params derive SPEC.yaml [--out P.yaml] [--sdf OUT.sdf] [--px4 OUT.params] [--airframe OUT]
    rotortwin params check P.yaml
    rotortwin params export P.yaml [--sdf OUT.sdf] [--px4 OUT.params] [--airframe OUT]
    rotortwin params from-ulog FLIGHT.ulg --out P.yaml [--mass-kg M] [--arm-m L] [--name N]
    rotortwin params from-ulog A.ulg B.ulg ... --out VEHICLE.yaml [--pool latest|all]   # the vehicle twin

``derive`` runs the Búho Negro pipeline (:mod:`twin_nodes.vehicle.derive`) on a
derivation spec and prints each derived quantity with its formula; ``--out``
writes the params file (with the table as its comment header).  ``--sdf``
writes the Gazebo motor plugin blocks, ``--px4`` a QGroundControl ``.params``
table and ``--airframe`` ``param set-default`` lines (:mod:`twin_nodes.vehicle.export_px4`).
``from-ulog`` builds the nominal twin of the vehicle that flew a PX4 log from the log's
parameters and identification on the flight (:mod:`twin_nodes.identify.nominal`); the
file's header lists every value's source.

Every output is prepared and every output path checked before anything is
written, so a bad input leaves no file behind and overwrites nothing.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from twin_nodes.cli.paths import declare
from twin_nodes.vehicle.derive import derivation_header, derive, load_spec
from twin_nodes.base.errors import ParamsError
from twin_nodes.cli.options import MASS_KG, finite_float
from twin_nodes.vehicle.export_px4 import px4_airframe_script, qgc_params_table, sdf_motor_plugins
from twin_nodes.vehicle.params import VehicleParams, load_params, write_params


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("params", help="derive, check and export vehicle parameter files",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="params_command", metavar="ACTION")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    d = sub.add_parser("derive", help="run the parameter pipeline on a derivation spec")
    io = declare(d)
    io.input("spec", help="derivation spec YAML (e.g. params/derive_buho_negro.yaml)")
    io.output("--out", help="write the derived params YAML here")
    _export_args(d)
    d.set_defaults(func=_cmd_derive)

    c = sub.add_parser("check", help="validate a params file and print hover speed, command and T/W")
    declare(c).input("params", help="params YAML")
    c.set_defaults(func=_cmd_check)

    e = sub.add_parser("export", help="write Gazebo SDF motor plugins and PX4 parameters for a params file")
    declare(e).input("params", help="params YAML")
    _export_args(e)
    e.set_defaults(func=_cmd_export)

    f = sub.add_parser("from-ulog", help="build the params of the vehicle that flew a PX4 log, from the log itself")
    io = declare(f)
    io.input("ulog", nargs="+", help="PX4 flight log(s) (.ulg); several logs of one vehicle: the vehicle twin "
             "pooled over its free flights, each value with its uncertainty and flight-to-flight scatter")
    io.output("--out", required=True, help="write the params YAML here")
    f.add_argument("--mass-kg", type=MASS_KG, help="take-off mass [kg] (else the airframe's typical mass, stated)")
    f.add_argument("--arm-m", type=finite_float(0.01, 100.0, unit="m"), help="centre-to-rotor distance [m] for logs whose layout is normalised")
    f.add_argument("--name", help="vehicle name in the file")
    f.add_argument("--pool", choices=("latest", "all"), default="latest",
                   help="several logs: pool the vehicle as it last flew (its latest motor configuration: outputs and "
                        "PWM limits; the flights since its latest change; default) or every flight of the majority's "
                        "motor configuration (all)")
    f.set_defaults(func=_cmd_from_ulog)


def _export_args(p: argparse.ArgumentParser) -> None:
    io = declare(p)
    io.output("--sdf", help="write MulticopterMotorModel <plugin> blocks here")
    io.output("--px4", help="write a QGroundControl .params table here")
    io.output("--airframe", help="write PX4 airframe 'param set-default' lines here")


def _summary(vp: VehicleParams) -> str:
    r = vp.rotors
    tw = r.count * r.thrust_at_full_command_n / (vp.mass_kg * vp.gravity_m_s2)
    rows = [
        ("file", vp.source),
        ("name", vp.name),
        ("rotors", f"{r.count} ({r.thrust_model})"),
        ("mass", f"{vp.mass_kg:.4g} kg"),
        ("hover omega", f"{vp.hover_omega_rad_s:.2f} rad/s ({vp.hover_omega_rad_s * 60 / 6.283185307179586:.0f} rpm)"
                        + ("" if r.thrust_model == "omega_squared" else ", reported speed only")),
        ("hover command", f"{vp.hover_command:.4f} (of 0..1)"),
        ("T/W at full command", f"{tw:.3f}"),
        ("thrust per rotor at full", f"{r.thrust_at_full_command_n:.4g} N"),
    ]
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


def _exports(vp: VehicleParams, args: argparse.Namespace) -> list[tuple[str, str]]:
    out = []
    if args.sdf:
        out.append((args.sdf, sdf_motor_plugins(vp)))
    if args.px4:
        out.append((args.px4, qgc_params_table(vp)))
    if args.airframe:
        out.append((args.airframe, px4_airframe_script(vp)))
    return out


def _write_text(path: str, text: str) -> None:
    """An output (staged by the CLI's guard: renamed into place only when the command succeeded)."""
    Path(path).write_text(text, encoding="utf-8")


def _cmd_derive(args: argparse.Namespace) -> int:
    spec = load_spec(args.spec)
    d = derive(spec, args.spec)
    exports = _exports(d.params, args)
    print(d.table())
    print()
    print(_summary(d.params))
    notes = spec.get("notes", "")
    if args.out:
        header = derivation_header(d, args.spec, notes if isinstance(notes, str) else "")
        try:
            write_params(d.params, args.out, header)
        except OSError as exc:
            raise ParamsError(args.out, "<output>", f"cannot write ({exc.strerror or exc})") from None
    for path, text in exports:
        _write_text(path, text)
    return 0


def _cmd_check(args: argparse.Namespace) -> int:
    vp = load_params(args.params)
    print(_summary(vp))
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    vp = load_params(args.params)
    exports = _exports(vp, args)
    if not exports:
        raise ParamsError(args.params, "<arguments>", "nothing to export: give --sdf, --px4 and/or --airframe")
    for path, text in exports:
        _write_text(path, text)
    return 0


def _cmd_from_ulog(args: argparse.Namespace) -> int:
    from twin_nodes.identify.nominal import nominal_from_log
    from twin_nodes.logs.ulog_io import read_ulog

    if len(args.ulog) > 1:
        from twin_nodes.fleet.vehicle_twin import build

        vt = build(args.ulog, mass_kg=args.mass_kg, arm_m=args.arm_m, name=args.name, state=args.pool)
        print(vt.header)
        print()
        print(_summary(vt.params))
        try:
            write_params(vt.params, args.out, vt.header)
        except OSError as exc:
            raise ParamsError(args.out, "<output>", f"cannot write ({exc.strerror or exc})") from None
        return 0
    nom = nominal_from_log(read_ulog(args.ulog[0]), mass_kg=args.mass_kg, arm_m=args.arm_m, name=args.name)
    print(nom.header())
    print()
    print(_summary(nom.params))
    try:
        write_params(nom.params, args.out, nom.header())
    except OSError as exc:
        raise ParamsError(args.out, "<output>", f"cannot write ({exc.strerror or exc})") from None
    return 0
